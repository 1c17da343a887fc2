"""One name for every elevation source a user or a bag can ask for.

``open_dem_source(spec)`` accepts:

* ``""``, ``"jacksboro"`` or any ``"matplotlib:..."`` name: the embedded USGS DEM;
* ``"synthetic"`` or ``"synthetic:seed=7,size=1024,gsd=5"``: the drainage terrain of
  :mod:`.synthetic_terrain`, placed in UTM zone 13N (a made-up place in the Colorado
  Rockies), rebuilt identically from its parameters wherever it is needed;
* a file path (``.asc``, ``.tif``, ``.hgt``, ``.npz``): :func:`.dem_io.open_dem`.
"""

from __future__ import annotations

from .dem_io import Dem, DemError, open_dem, sample_dem
from .synthetic_terrain import synthetic_dem

SYNTHETIC_DEFAULTS = {"seed": 7, "size": 1024, "gsd": 5.0}
_SYNTHETIC_CORNER = (440_000.0, 4_440_000.0)  # UTM 13N easting/northing of the NW corner


def parse_synthetic(spec: str) -> dict:
    """``"synthetic:seed=3,size=512"`` -> {"seed": 3, "size": 512, "gsd": 5.0}."""
    params = dict(SYNTHETIC_DEFAULTS)
    _, _, rest = spec.partition(":")
    for item in filter(None, (p.strip() for p in rest.split(","))):
        key, sep, value = item.partition("=")
        if not sep or key not in params:
            raise DemError(f"{spec}: expected synthetic:seed=N,size=N,gsd=X, got '{item}'")
        params[key] = type(params[key])(value)
    return params


def open_dem_source(spec: str) -> Dem:
    """The DEM a source name stands for (see the module docstring)."""
    spec = (spec or "").strip()
    if not spec or spec == "jacksboro" or spec.startswith("matplotlib:"):
        return sample_dem()
    if spec == "synthetic" or spec.startswith("synthetic:"):
        p = parse_synthetic(spec)
        z = synthetic_dem(p["size"], p["gsd"], seed=p["seed"])
        x0, y0 = _SYNTHETIC_CORNER
        return Dem.from_array(z, (x0, p["gsd"], 0.0, y0, 0.0, -p["gsd"]), crs="EPSG:32613",
                              name=f"synthetic:seed={p['seed']},size={p['size']},"
                                   f"gsd={p['gsd']:g}")
    return open_dem(spec)
