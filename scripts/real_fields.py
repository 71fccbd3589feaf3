#!/usr/bin/env python3
"""Copy the real geophysical fields a Python package ships offline into target/real-fields/,
where config/experiment-real.toml reads them (a fresh clone has no data of its own).

eofs 2.0 (pip, installed by scripts/test.sh) ships two NetCDF-3 files from public reanalyses:
  sst_ndjfm_anom.nc  NOAA ERSST v3b, November-March mean sea-surface temperature anomaly (K),
                     5-degree grid over the Pacific, 18 x 30 cells, 50 winters, land as _FillValue;
  hgt_djf.nc         NCEP/NCAR reanalysis, December-February mean geopotential height (m) at
                     500 hPa, 2.5-degree grid over the North Atlantic, 29 x 49 cells, 65 winters.
Exit 0 copied, 2 if eofs is not installed (say how to install it).
"""
import os
import shutil
import sys

try:
    import eofs
except ImportError:
    print("real_fields.py: eofs is not installed (python3 -m pip install eofs==2.0.0)", file=sys.stderr)
    sys.exit(2)

src = os.path.join(os.path.dirname(eofs.__file__), "examples", "example_data")
dst = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "target", "real-fields")
os.makedirs(dst, exist_ok=True)
for name in ("sst_ndjfm_anom.nc", "hgt_djf.nc"):
    shutil.copyfile(os.path.join(src, name), os.path.join(dst, name))
    print(os.path.normpath(os.path.join(dst, name)))
