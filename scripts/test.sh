#!/usr/bin/env bash
# The whole test suite, from a fresh clone: installs what the cross-checks need, builds the
# workspace once in release (tests run in the same profile as the binaries), runs every test.
set -euo pipefail
cd "$(dirname "$0")/.."
# Python peers used by cross-check tests (PyDMD, odmd, pysensors, numpy/scipy) and the
# Python Zenoh client that reads the fleet's model (eclipse-zenoh, the same 1.10 line as the
# Rust side, and cbor2).
# xarray reads the NetCDF a run writes, mcap its recording (its Foxglove channels decoded with
# Foxglove's published protobuf schemas, foxglove-schemas-protobuf, and jsonschema; websockets
# is the Foxglove WebSocket test client); MAVSDK (its native binding, v4)
# is a second ground-station stack against the simulated autopilot. eofs ships two real NetCDF
# files with holes (an SST anomaly with land, a 500 hPa height with a singleton level). The IOOS
# compliance-checker judges estimate.nc by CF-1.8 and ACDD-1.3 and readings.nc by CF-1.8, as a
# data centre does, and cf_xarray finds readings.nc's trajectory roles and flags; netCDF4
# writes the NetCDF-4 files the reader is tested on, as data centres make them.
if ! python3 -c "import numpy, scipy, pydmd, odmd, pysensors, zenoh, cbor2, pymavlink, xarray, mcap, mavsdk.plugins.geofence, eofs, foxglove_schemas_protobuf, jsonschema, websockets, compliance_checker, netCDF4, cf_xarray" 2>/dev/null; then
  echo "== installing Python peers (numpy scipy pydmd odmd python-sensors eclipse-zenoh cbor2 pymavlink xarray mcap mavsdk eofs foxglove-schemas-protobuf jsonschema websockets compliance-checker netCDF4 cf_xarray)"
  python3 -m pip install --quiet --disable-pip-version-check --root-user-action=ignore \
    numpy scipy pydmd odmd python-sensors eclipse-zenoh==1.10.2 cbor2 pymavlink==2.4.50 xarray mcap mavsdk==4.1.0 eofs==2.0.0 \
    foxglove-schemas-protobuf==0.4.0 jsonschema websockets==15.0.1 compliance-checker==6.1.0 netCDF4 cf_xarray==0.11.3
fi
# Debian's chromium for the live view's browser test, gdal-bin for the GeoTIFF test, DejaVu
# for the charts' text, nftables and iproute2's tc for the radio test's shaped link, and the
# system's zstd for the recordings' compression (below).
missing=()
command -v pkg-config >/dev/null || missing+=(pkg-config)
pkg-config --exists libzstd 2>/dev/null || missing+=(libzstd-dev)
command -v nft >/dev/null || missing+=(nftables)
command -v tc >/dev/null || missing+=(iproute2)
command -v chromium >/dev/null || missing+=(chromium)
command -v gdalinfo >/dev/null || missing+=(gdal-bin)
[ -e /usr/share/fonts/truetype/dejavu/DejaVuSans.ttf ] || missing+=(fonts-dejavu-core)
if [ ${#missing[@]} -gt 0 ]; then
  echo "== installing ${missing[*]} (the live view's browser test, the GeoTIFF test, the charts' font, the radio test, zstd)"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -q >/dev/null && apt-get install -y -q "${missing[@]}" >/dev/null
fi
# mdBook builds the user's guide (docs/book.toml); installed here, before the lint settings
# below, which would lint its sources as if they were ours.
if ! command -v mdbook >/dev/null; then
  echo "== installing mdbook (the guide's builder)"
  cargo install mdbook --version "^0.4" --locked --no-default-features --quiet
fi
echo "== documents (the guide builds; every relative link of the Markdown resolves)"
mdbook build docs
python3 scripts/check_links.py
echo "== house style (rustfmt.toml; the code's shape; clippy runs in the build below)"
cargo fmt --all --check
# No import loops in any crate, no sleeping in a loop in the vehicle node and its bridge, no
# struct's field list written twice, no over-long function or over-wide impl
# (scripts/check_structure.py says what it checks; its own test plants each and sees it found).
python3 scripts/check_structure.py
python3 scripts/test_check_structure.py
# Clippy lints the workspace as it is built, with warnings as errors: `clippy-driver` (the
# compiler `cargo clippy` runs) compiles the workspace's own crates, so one build both lints and
# makes the binaries the tests run (a separate `cargo clippy` pass type-checked the whole
# dependency tree a second time: 4 of the suite's 38 minutes). Dependencies are built by rustc
# as always, their lints capped by cargo. The recordings' zstd is the system's (libzstd-dev)
# rather than the copy of its C sources `zstd-sys` compiles (2 minutes of the build); a user's
# `cargo build` still compiles that copy. These settings are the test build's own: every cargo
# command below runs with them, so the tests reuse the one build.
RUSTC_WORKSPACE_WRAPPER="$(rustup which clippy-driver 2>/dev/null || command -v clippy-driver || true)"
if ! "${RUSTC_WORKSPACE_WRAPPER:-false}" --version 2>/dev/null | grep -q clippy; then
  echo "test.sh: clippy-driver not found (rustup component add clippy): the build would not be linted" >&2
  exit 1
fi
export RUSTC_WORKSPACE_WRAPPER
export RUSTFLAGS="-D warnings" ZSTD_SYS_USE_PKG_CONFIG=1
# The lints must be able to fail: a crate with two of clippy's warnings must not build.
probe="$(mktemp -d)"
cargo new -q --vcs none --name lint_probe "$probe/lint_probe"
printf 'fn main() {\n    let v = vec![1];\n    for i in 0..v.len() {\n        println!("{}", v[i]);\n    }\n}\n' \
  > "$probe/lint_probe/src/main.rs"
if cargo build -q --manifest-path "$probe/lint_probe/Cargo.toml" 2> "$probe/lints.txt" \
  || ! grep -q "clippy::needless_range_loop" "$probe/lints.txt"; then
  echo "test.sh: the build did not refuse clippy's warnings in a probe crate ($probe): lints are not running" >&2
  exit 1
fi
rm -rf "$probe"
echo "== building and linting (release; clippy with warnings as errors)"
cargo build --release --workspace --all-targets
echo "== testing (release)"
cargo test --release --workspace -- --skip malformed_inputs_never_panic_a_decoder
echo "== fuzzing the decoders (release; prints how many inputs)"
# (--workspace keeps the features of the build above: no second build of zenoh)
cargo test --release --workspace --test fuzz -- --nocapture
