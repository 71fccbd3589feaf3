//! The documents against what they describe: the command-line reference is what the binaries
//! say, the files' JSON Schema takes every bundled file and refuses a key it does not know,
//! troubleshooting names every kind of refusal, the wire protocol's page every key and the
//! schema version, and every relative link of the Markdown resolves. (The files' reference is
//! compared with the types in `fleet`'s own tests.)

use hetfleet_tests::{root, run, scratch};
use std::process::Command;
use strum::VariantNames;

/// The binaries a user runs, and `fleet`'s subcommands (and `fleet bench`'s), in the order the
/// reference gives them.
const BINARIES: [&str; 7] = [
    "fleet",
    "model-server",
    "vehicle",
    "gcs-gateway",
    "sim-autopilot",
    "fleet-watch",
    "fleet-operator",
];

/// `<binary> <args> --help`, as the binary prints it.
fn help(binary: &str, args: &[&str]) -> String {
    let mut all: Vec<&str> = args.to_vec();
    all.push("--help");
    let out = run(binary, &all);
    assert!(
        out.status.success(),
        "{binary} {args:?} --help: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap().trim_end().to_string()
}

/// The subcommands a help text lists (its `Commands:` section, `help` left out).
fn subcommands(help: &str) -> Vec<String> {
    let Some(at) = help.find("Commands:\n") else {
        return vec![];
    };
    help[at + 10..]
        .lines()
        .take_while(|l| l.starts_with("  "))
        .filter(|l| !l.starts_with("   "))
        .filter_map(|l| l.split_whitespace().next().map(String::from))
        .filter(|c| c != "help")
        .collect()
}

/// The command-line reference page made from the binaries' own help (clap's).
fn cli_markdown() -> String {
    let mut md = String::from(
        "# The command line\n\n\
         Every binary's `--help`, as it prints it (made by the test `the_cli_reference_is_what_the_binaries_say` \
         in `tests/tests/docs.rs`: `HETFLEET_BLESS=1 cargo test --release -p hetfleet-tests --test docs` \
         writes it again). Exit codes: [troubleshooting](../guide/troubleshooting.md).\n",
    );
    for binary in BINARIES {
        let mut queue: Vec<Vec<String>> = vec![vec![]];
        while let Some(path) = queue.pop() {
            let args: Vec<&str> = path.iter().map(String::as_str).collect();
            let text = help(binary, &args);
            let level = "#".repeat(2 + path.len().min(2));
            md.push_str(&format!(
                "\n{level} `{}`\n\n```text\n{text}\n```\n",
                [binary]
                    .iter()
                    .chain(args.iter())
                    .copied()
                    .collect::<Vec<_>>()
                    .join(" ")
            ));
            for sub in subcommands(&text).into_iter().rev() {
                let mut next = path.clone();
                next.push(sub);
                queue.push(next);
            }
        }
    }
    md
}

#[test]
fn the_cli_reference_is_what_the_binaries_say() {
    let path = root().join("docs/reference/cli.md");
    let made = cli_markdown();
    if std::env::var_os("HETFLEET_BLESS").is_some() {
        std::fs::write(&path, &made).unwrap();
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        committed == made,
        "docs/reference/cli.md is not what the binaries say: make it again with \
         HETFLEET_BLESS=1 cargo test --release -p hetfleet-tests --test docs"
    );
}

/// Every refusal kind (a variant of the errors that are the operator's to fix) is named in
/// troubleshooting, with its cause and fix; the one kind that is ours (a file the disk would
/// not write) is not a refusal.
#[test]
fn troubleshooting_names_every_kind_of_refusal() {
    let page = std::fs::read_to_string(root().join("docs/guide/troubleshooting.md")).unwrap();
    let kinds = [
        ("ConfigError", fleet_mission::config::ConfigError::VARIANTS),
        ("DatasetError", fleet_math::process::error::DatasetError::VARIANTS),
        ("TruthError", fleet_math::process::truth::TruthError::VARIANTS),
    ];
    let missing: Vec<String> = kinds
        .iter()
        .flat_map(|(ty, variants)| variants.iter().map(move |v| format!("{ty}::{v}")))
        .filter(|k| k != "DatasetError::Io")
        .filter(|k| !page.contains(&format!("`{k}`")))
        .collect();
    assert!(
        missing.is_empty(),
        "refusals troubleshooting does not name: {missing:?}"
    );
}

/// `fleet schema` checks what the files hold as the binaries do: every bundled mission and
/// experiment passes, and a key neither knows is refused (Python's `jsonschema`, draft
/// 2020-12, as an editor would check a file).
#[test]
fn the_json_schema_takes_every_bundled_file_and_refuses_an_unknown_key() {
    let dir = scratch("schema");
    for kind in ["mission", "experiment"] {
        let out = run("fleet", &["schema", kind]);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        std::fs::write(dir.join(format!("{kind}.schema.json")), &out.stdout).unwrap();
    }
    let script = r#"
import glob, json, sys, tomllib, jsonschema
root, dir = sys.argv[1], sys.argv[2]
for kind in ("mission", "experiment"):
    schema = json.load(open(f"{dir}/{kind}.schema.json"))
    check = jsonschema.Draft202012Validator(schema)
    files = sorted(glob.glob(f"{root}/config/{kind}*.toml"))
    assert files, kind
    for f in files:
        errors = [e.message for e in check.iter_errors(tomllib.load(open(f, "rb")))]
        assert not errors, (f, errors)
    planted = tomllib.load(open(files[0], "rb"))
    planted["team"] = dict(planted.get("team", {}), boat = 3)
    assert list(check.iter_errors(planted)), f"{kind}: an unknown [team] key passed"
print("ok")
"#;
    let out = Command::new("python3")
        .args(["-c", script, root().to_str().unwrap(), dir.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The wire protocol's page names every key the nodes use, the Zenoh encoding and the schema
/// version, as the code spells them: a key, an encoding or a version changed in the code and not
/// on the page fails here.
#[test]
fn the_protocol_reference_names_every_key_the_encoding_and_the_schema_version() {
    use fleet_mission::protocol::{keys::Keys, ENCODING, SCHEMA_VERSION};
    let page = std::fs::read_to_string(root().join("docs/reference/protocol.md")).unwrap();
    let k = Keys::new("m").unwrap();
    let id = "<id>";
    let keys = [
        k.measurements(id),
        k.telemetry(id),
        k.ack(id),
        k.mavlink(id),
        k.gcs(id),
        k.model_latest(),
        k.plan(id),
        k.alive(id),
        k.server_status(),
        k.sensor_override(id),
    ];
    for key in keys {
        let leaf = key.strip_prefix("fleet/m/").expect("a key under fleet/<mission>/");
        assert!(
            page.contains(&format!("`{leaf}`")),
            "docs/reference/protocol.md does not name `{leaf}`"
        );
    }
    assert!(
        page.contains(ENCODING),
        "docs/reference/protocol.md does not give the encoding {ENCODING}"
    );
    let version = format!("{{\"v\": {SCHEMA_VERSION},");
    assert!(
        page.contains(&version),
        "docs/reference/protocol.md does not give schema version {SCHEMA_VERSION}"
    );
}

/// Every relative link of the README, the guide and the examples resolves
/// (`scripts/check_links.py`); and the link check itself finds a planted broken one.
#[test]
fn every_relative_link_resolves() {
    let out = Command::new("python3")
        .arg(root().join("scripts/check_links.py"))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stdout));
    let dir = scratch("links");
    std::fs::create_dir_all(dir.join("docs")).unwrap();
    std::fs::write(
        dir.join("README.md"),
        "[gone](docs/nothing.md) [fine](README.md#top)\n# Top\n",
    )
    .unwrap();
    std::fs::create_dir_all(dir.join("scripts")).unwrap();
    std::fs::copy(
        root().join("scripts/check_links.py"),
        dir.join("scripts/check_links.py"),
    )
    .unwrap();
    let out = Command::new("python3")
        .arg(dir.join("scripts/check_links.py"))
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(
        !out.status.success() && said.contains("docs/nothing.md: no such file") && !said.contains("#top"),
        "{said}"
    );
}

/// The guide's shell examples: every block marked `sh` (a `sh no-run` block needs what CI does
/// not have: hardware, a second machine, root and a running mission, or ten minutes; the
/// process tests run those commands), each line as a user would type it, from a directory
/// holding the repository's `config/` and `scripts/`, with the binaries on the `PATH`.
fn shell_examples() -> Vec<(String, String)> {
    let mut out = vec![];
    let mut pages: Vec<_> = std::fs::read_dir(root().join("docs/guide"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    pages.sort();
    for page in pages {
        let text = std::fs::read_to_string(&page).unwrap();
        let mut lines = text.lines();
        while let Some(line) = lines.next() {
            let indent = line.len() - line.trim_start().len();
            if line.trim() != "```sh" {
                continue;
            }
            let block: Vec<&str> = lines
                .by_ref()
                .take_while(|l| l.trim() != "```")
                .map(|l| l.get(indent..).unwrap_or(l.trim_start()))
                .collect();
            out.push((
                page.file_name().unwrap().to_string_lossy().into_owned(),
                block.join("\n"),
            ));
        }
    }
    out
}

#[test]
fn every_shell_example_in_the_guide_runs() {
    let examples = shell_examples();
    assert!(examples.len() >= 4, "{} runnable examples", examples.len());
    for (n, (page, block)) in examples.iter().enumerate() {
        let dir = scratch(&format!("guide-{n}"));
        std::fs::create_dir_all(dir.join("target")).unwrap();
        for link in ["config", "scripts"] {
            let _ = std::os::unix::fs::symlink(root().join(link), dir.join(link));
        }
        let _ = std::os::unix::fs::symlink(root().join("target/release"), dir.join("target/release"));
        let port = hetfleet_tests::free_port();
        let script = format!(
            "set -euo pipefail\nexport PATH={}:$PATH\n{}",
            root().join("target/release").display(),
            block.replace("127.0.0.1:8080", &format!("127.0.0.1:{port}"))
        );
        let out = Command::new("timeout")
            .args(["600", "bash", "-c", &script])
            .current_dir(&dir)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{page}, example {n}:\n{block}\n--- stdout\n{}\n--- stderr\n{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }
}
