"""The lierk application, built on the library's public API (`import lierk`).

Each module is imported when first used (``lierk.app.scene``), so that
importing one part loads neither matplotlib nor the others:

- `scene`, `scene_schema`: scene files (TOML) -> a problem, a solver and run
  settings; the schema they follow (`lierk schema` prints it);
- `simulation`: a scene's run, diagnostics and figures written to a folder;
- `cli`, `cli_arguments`: the ``lierk`` command;
- `accuracy`: work-precision reports of a scene's solvers;
- `omega_sweep`, `store`, `segments`: resumable sweeps of omega0 on disk;
- `plot`: figures and animations of a `lierk.Solution`;
- `diagnostics`: invariants' drift, orthogonality and the flip;
- `distributed`: multi-process set-up (``jax.distributed``);
- `cache`, `compilations`: the persistent compilation cache, and counting
  what a block compiles;
- `demo`: the report's cases, end to end (``python -m lierk.app.demo``).
"""

import importlib as _importlib

_MODULES = (
    "accuracy",
    "cache",
    "cli",
    "cli_arguments",
    "compilations",
    "demo",
    "diagnostics",
    "distributed",
    "omega_sweep",
    "plot",
    "scene",
    "scene_schema",
    "segments",
    "simulation",
    "store",
)


def __getattr__(name: str):
    if name in _MODULES:
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted([*globals(), *_MODULES])
