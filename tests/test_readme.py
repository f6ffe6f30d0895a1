"""The README's quick start runs as written and says what it shows."""

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def test_quick_start_runs_and_meets_its_target():
    block = re.search(r"## Quick start\n\n```python\n(.*?)```", README.read_text(), re.S).group(1)
    env: dict = {}
    exec(compile(block, "README.md (quick start)", "exec"), env)
    assert env["J"].shape == (3, 3, 3) and np.all(np.isfinite(env["J"]))
    sol = env["sol"]
    assert int(sol.result) == 0 and float(sol.error_estimate[-1]) <= 1e-9
    R = env["final_attitude"](env["jnp"].array([[1.0, 0.05, 0.0], [0.1, 1.0, 0.0]]))
    assert R.shape == (2, 3, 3)
    # Dense output and events, as the comments say.
    assert env["R"].shape == (2000, 3, 3) and env["m"].shape == (2000, 3)
    flips = np.asarray(env["flips"].events.ts[: int(env["flips"].events.count)])
    np.testing.assert_allclose(flips, [11.81536, 35.44609, 59.07681], atol=5e-6)
    stop = env["stop"]
    assert int(stop.result) == 6 and float(stop.ts[-1]) == float(stop.events.ts[0]) and abs(float(stop.R[-1, 0, 0])) < 1e-12
