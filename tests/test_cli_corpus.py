"""A corpus of malformed scenes: each must end ``lierk simulate`` with a
non-zero exit status and exactly one line on stderr, starting with the
program's name, naming the problem; never a traceback, and never after
integrating (the errors come from loading).

Runs in-process (``cli.main``), like ``tests/test_cli.py``: a subprocess per
file would spend a second each importing JAX.
"""

from __future__ import annotations

import pytest

import lierk.app.scene
from lierk.app import cli


def scene(
    body: str = 'kind = "tee_handle"',
    initial: str = "omega = [1.0, 0.05, 0.0]",
    run: str = 'solver = "RKMK4"\ndt = 0.01\nt1 = 1.0',
    effects: str = "",
    top: str = 'name = "corpus"',
) -> str:
    """A scene file; each argument replaces the body of one table (``effects``:
    whole ``[[effects]]`` tables)."""
    return f"{top}\n[body]\n{body}\n[initial]\n{initial}\n{effects}\n[run]\n{run}\n"


VALID = scene()
ADAPTIVE = 'solver = "DP54"\nrtol = 1e-8\nt1 = 1.0'
TENSOR = 'kind = "tensor"\ninertia = [1.0, 2.0, 3.0]'
DAMPING = '[[effects]]\nkind = "damping"\nc = 0.1\n'


def effect(text: str) -> str:
    return f"[[effects]]\n{text}\n"


# (id, file contents (str, or bytes written as they are), a fragment of the expected message)
CORPUS = [
    # --- wrong types
    ("name-not-string", scene(top="name = 5"), "name must be a string, got 5"),
    ("description-list", scene(top="description = [1, 2]"), "description must be a string"),
    (
        "body-not-table",
        'body = 5\n[initial]\nomega = [1.0, 0.0, 0.0]\n[run]\nsolver = "RKMK4"\ndt = 0.1\nt1 = 1.0\n',
        "body must be a table, got 5",
    ),
    (
        "initial-not-table",
        'initial = "up"\n[body]\nkind = "tee_handle"\n[run]\nsolver = "RKMK4"\ndt = 0.1\nt1 = 1.0\n',
        "initial must be a table",
    ),
    (
        "run-not-table",
        'run = [1, 2]\n[body]\nkind = "tee_handle"\n[initial]\nomega = [1.0, 0.0, 0.0]\n',
        "run must be a table, got [1, 2]",
    ),
    ("omega-string", scene(initial='omega = "fast"'), "initial.omega must be a list of 3 numbers"),
    ("omega-entry-string", scene(initial='omega = [1.0, "a", 0.0]'), "initial.omega[1] must be a finite number"),
    ("omega-entry-bool", scene(initial="omega = [true, 0.0, 0.0]"), "initial.omega[0] must be a finite number"),
    ("omega-nested", scene(initial="omega = [[1.0], [0.0], [0.0]]"), "initial.omega[0] must be a finite number"),
    ("omega-table", scene(initial="omega = {x = 1.0}"), "initial.omega must be a list of 3 numbers"),
    ("t1-string", scene(run='solver = "RKMK4"\ndt = 0.01\nt1 = "ten"'), "run.t1 must be a finite number, got 'ten'"),
    ("dt-bool", scene(run='solver = "RKMK4"\ndt = true\nt1 = 1.0'), "run.dt must be a finite number, got True"),
    ("t1-date", scene(run='solver = "RKMK4"\ndt = 0.01\nt1 = 1979-05-27'), "run.t1 must be a finite number"),
    ("solver-number", scene(run="solver = 4\ndt = 0.01\nt1 = 1.0"), "run.solver = 4 is not allowed"),
    (
        "save-every-float",
        scene(run='solver = "RKMK4"\ndt = 0.01\nt1 = 1.0\nsave_every = 2.5'),
        "run.save_every must be a positive integer",
    ),
    ("n-save-float", scene(run=ADAPTIVE + "\nn_save = 100.0"), "run.n_save must be a positive integer"),
    ("effects-string", scene(top='name = "corpus"\neffects = "gravity"'), "effects must be an array of tables"),
    ("effects-numbers", scene(top='name = "corpus"\neffects = [1, 2]'), "effects[0] must be a table, got 1"),
    ("body-kind-list", scene(body='kind = ["box"]'), "body.kind = ['box'] is not allowed"),
    (
        "tensor-inertia-string",
        scene(body='kind = "tensor"\ninertia = "big"'),
        "body.inertia must be a list of 3 numbers",
    ),
    (
        "torque-string",
        scene(effects=effect('kind = "body_torque"\ntorque = "x"')),
        "effects[0].torque must be a list of 3 numbers",
    ),
    ("damping-c-string", scene(effects=effect('kind = "damping"\nc = "0.1"')), "effects[0].c must be a finite number"),
    ("parts-string", scene(body='kind = "composite"\nparts = "one"'), "body.parts must be a non-empty array of tables"),
    ("parts-empty", scene(body='kind = "composite"\nparts = []'), "body.parts must be a non-empty array of tables"),
    ("part-number", scene(body='kind = "composite"\nparts = [1]'), "body.parts[0] must be a table, got 1"),
    # --- missing tables and keys
    (
        "no-body",
        'name = "x"\n[initial]\nomega = [1.0, 0.0, 0.0]\n[run]\nsolver = "RKMK4"\ndt = 0.1\nt1 = 1.0\n',
        "missing required key 'body'",
    ),
    (
        "no-initial",
        'name = "x"\n[body]\nkind = "tee_handle"\n[run]\nsolver = "RKMK4"\ndt = 0.1\nt1 = 1.0\n',
        "missing required key 'initial'",
    ),
    (
        "no-run",
        'name = "x"\n[body]\nkind = "tee_handle"\n[initial]\nomega = [1.0, 0.0, 0.0]\n',
        "missing required key 'run'",
    ),
    ("no-omega", scene(initial='attitude = "identity"'), "initial: missing required key 'omega'"),
    ("no-solver", scene(run="dt = 0.01\nt1 = 1.0"), "run: missing required key 'solver'"),
    ("no-t1", scene(run='solver = "RKMK4"\ndt = 0.01'), "run: missing required key 't1'"),
    ("no-step", scene(run='solver = "RKMK4"\nt1 = 1.0'), "give exactly one of 'dt'"),
    ("dt-and-rtol", scene(run='solver = "DP54"\nt1 = 1.0\ndt = 0.1\nrtol = 1e-6'), "got dt, rtol"),
    ("box-no-lx", scene(body='kind = "box"\nmass = 1.0\nly = 1.0\nlz = 2.0'), "body: missing required key 'lx'"),
    ("body-no-kind", scene(body="mass = 1.0"), "body.kind is missing"),
    ("torque-missing", scene(effects=effect('kind = "body_torque"')), "effects[0]: missing required key 'torque'"),
    (
        "rtol-fixed-solver",
        scene(run='solver = "RKMK4"\nrtol = 1e-6\nt1 = 1.0'),
        "adaptive solvers (for rtol): RKF45, DP54, DOP853",
    ),
    # --- unknown keys
    ("unknown-top", scene(top='name = "corpus"\ncolour = "red"'), "unknown key 'colour'"),
    ("unknown-table", VALID + "[extra]\nx = 1\n", "unknown key 'extra'"),
    ("unknown-body-key", scene(body='kind = "tee_handle"\nspin = 1.0'), "body: unknown key 'spin'"),
    ("unknown-initial-key", scene(initial="omega = [1.0, 0.0, 0.0]\nspin = 1.0"), "initial: unknown key 'spin'"),
    ("unknown-run-key", scene(run='solver = "RKMK4"\ndt = 0.01\nt1 = 1.0\nsteps = 10'), "run: unknown key 'steps'"),
    ("unknown-effect-key", scene(effects=effect('kind = "damping"\nc = 0.1\nk = 1.0')), "effects[0]: unknown key 'k'"),
    ("tee-mass", scene(body='kind = "tee_handle"\nmass = 1.0'), "body: unknown key 'mass'"),
    # --- misspelt: the closest name is suggested
    (
        "misspelt-key",
        scene(initial="omgea = [1.0, 0.0, 0.0]"),
        "initial: unknown key 'omgea' (= [1.0, 0.0, 0.0]); did you mean 'omega'?; allowed keys:",
    ),
    (
        "misspelt-kind",
        scene(effects=effect('kind = "gravty"\npivot = [0.0, 0.0, 0.0]')),
        "effects[0].kind = 'gravty' is not allowed; did you mean 'gravity'?; choose one of:",
    ),
    (
        "misspelt-choice",
        scene(run='solver = "RKMK4"\ndt = 0.01\nt1 = 1.0\nsave_evry = 2'),
        "did you mean 'save_every'?",
    ),
    (
        "atol-with-dt",
        scene(run='solver = "RKMK4"\ndt = 0.01\nt1 = 1.0\natol = 1e-6'),
        "run.atol applies to adaptive runs",
    ),
    # --- NaN, inf, negative and zero values
    ("omega-nan", scene(initial="omega = [nan, 0.0, 0.0]"), "initial.omega[0] must be a finite number, got nan"),
    ("omega-inf", scene(initial="omega = [1.0, -inf, 0.0]"), "initial.omega[1] must be a finite number, got -inf"),
    ("t1-nan", scene(run='solver = "RKMK4"\ndt = 0.01\nt1 = nan'), "run.t1 must be a finite number, got nan"),
    ("t1-negative", scene(run='solver = "RKMK4"\ndt = 0.01\nt1 = -1.0'), "run.t1 must be > 0, got -1.0"),
    ("t1-zero", scene(run='solver = "RKMK4"\ndt = 0.01\nt1 = 0'), "run.t1 must be > 0, got 0"),
    ("dt-zero", scene(run='solver = "RKMK4"\ndt = 0.0\nt1 = 1.0'), "run.dt must be > 0, got 0.0"),
    ("dt-negative", scene(run='solver = "RKMK4"\ndt = -0.01\nt1 = 1.0'), "run.dt must be > 0"),
    ("dt-inf", scene(run='solver = "RKMK4"\ndt = inf\nt1 = 1.0'), "run.dt must be a finite number, got inf"),
    ("rtol-zero", scene(run='solver = "DP54"\nrtol = 0.0\nt1 = 1.0'), "run.rtol must be > 0"),
    ("atol-negative", scene(run=ADAPTIVE + "\natol = -1e-9"), "run.atol must be > 0"),
    ("target-error-zero", scene(run='solver = "RKMK4"\ntarget_error = 0.0\nt1 = 1.0'), "run.target_error must be > 0"),
    ("sphere-radius-zero", scene(body='kind = "sphere"\nmass = 1.0\nradius = 0.0'), "body.radius must be > 0"),
    (
        "box-mass-negative",
        scene(body='kind = "box"\nmass = -1.0\nlx = 1.0\nly = 2.0\nlz = 3.0'),
        "body.mass must be > 0",
    ),
    (
        "cylinder-length-nan",
        scene(body='kind = "cylinder"\nmass = 1.0\nradius = 0.1\nlength = nan'),
        "body.length must be a finite number, got nan",
    ),
    ("tee-density-negative", scene(body='kind = "tee_handle"\ndensity = -6700.0'), "body.density must be > 0"),
    (
        "tensor-indefinite",
        scene(body='kind = "tensor"\ninertia = [1.0, -1.0, 1.0]'),
        "inertia must be positive definite",
    ),
    ("tensor-zero", scene(body='kind = "tensor"\ninertia = [0.0, 0.0, 0.0]'), "inertia must be positive definite"),
    ("tensor-nan", scene(body='kind = "tensor"\ninertia = [1.0, nan, 1.0]'), "body.inertia[1] must be a finite number"),
    (
        "tensor-asymmetric",
        scene(body='kind = "tensor"\ninertia = [[1.0, 0.5, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 3.0]]'),
        "inertia must be symmetric",
    ),
    ("damping-negative", scene(effects=effect('kind = "damping"\nc = -0.1')), "effects[0].c must be >= 0"),
    (
        "gravity-g-negative",
        scene(effects=effect('kind = "gravity"\npivot = [0.0, 0.0, 0.0]\ng = -9.81')),
        "effects[0].g must be >= 0",
    ),
    ("n-save-one", scene(run=ADAPTIVE + "\nn_save = 1"), "run.n_save must be >= 2"),
    (
        "save-every-zero",
        scene(run='solver = "RKMK4"\ndt = 0.01\nt1 = 1.0\nsave_every = 0'),
        "run.save_every must be a positive integer, got 0",
    ),
    ("max-steps-negative", scene(run=ADAPTIVE + "\nmax_steps = -5"), "run.max_steps must be a positive integer"),
    # --- orientations
    (
        "matrix-reflection",
        scene(initial="omega = [1.0, 0.0, 0.0]\nmatrix = [[1, 0, 0], [0, 1, 0], [0, 0, -1]]"),
        "initial.matrix: R0 must be a rotation matrix",
    ),
    (
        "matrix-scaled",
        scene(initial="omega = [1.0, 0.0, 0.0]\nmatrix = [[2, 0, 0], [0, 2, 0], [0, 0, 2]]"),
        "initial.matrix: R0 must be a rotation matrix",
    ),
    (
        "matrix-shear",
        scene(initial="omega = [1.0, 0.0, 0.0]\nmatrix = [[1, 0.1, 0], [0, 1, 0], [0, 0, 1]]"),
        "initial.matrix: R0 must be a rotation matrix",
    ),
    ("matrix-2x2", scene(initial="omega = [1.0, 0.0, 0.0]\nmatrix = [[1, 0], [0, 1]]"), "initial.matrix must be a 3x3"),
    (
        "matrix-short-row",
        scene(initial="omega = [1.0, 0.0, 0.0]\nmatrix = [[1, 0], [0, 1], [0, 0]]"),
        "initial.matrix[0] must be a list of 3 numbers",
    ),
    (
        "matrix-nan",
        scene(initial="omega = [1.0, 0.0, 0.0]\nmatrix = [[nan, 0, 0], [0, 1, 0], [0, 0, 1]]"),
        "initial.matrix[0][0] must be a finite number",
    ),
    (
        "quaternion-zero",
        scene(initial="omega = [1.0, 0.0, 0.0]\nquaternion = [0, 0, 0, 0]"),
        "initial.quaternion must be a nonzero quaternion",
    ),
    (
        "quaternion-three",
        scene(initial="omega = [1.0, 0.0, 0.0]\nquaternion = [1, 0, 0]"),
        "initial.quaternion must be a list of 4 numbers",
    ),
    (
        "quaternion-inf",
        scene(initial="omega = [1.0, 0.0, 0.0]\nquaternion = [inf, 0, 0, 0]"),
        "initial.quaternion[0] must be a finite number",
    ),
    (
        "euler-two",
        scene(initial="omega = [1.0, 0.0, 0.0]\neuler = [0.1, 0.2]"),
        "initial.euler must be a list of 3 numbers",
    ),
    (
        "attitude-upright",
        scene(initial='omega = [1.0, 0.0, 0.0]\nattitude = "upright"'),
        "initial.attitude = 'upright' is not allowed",
    ),
    (
        "two-orientations",
        scene(initial="omega = [1.0, 0.0, 0.0]\neuler = [0, 0, 0]\nquaternion = [1, 0, 0, 0]"),
        "give at most one of",
    ),
    (
        "part-reflection",
        scene(
            body='kind = "composite"\n[[body.parts]]\nkind = "sphere"\nmass = 1.0\nradius = 0.1\n'
            "matrix = [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]"
        ),
        "body.parts[0].matrix: R0 must be a rotation matrix",
    ),
    # --- effects
    ("effect-empty", scene(effects="[[effects]]\n"), "effects[0].kind is missing"),
    (
        "effect-unknown-kind",
        scene(effects=effect('kind = "magnetism"')),
        "effects[0].kind = 'magnetism' is not allowed",
    ),
    ("effect-duplicate", scene(effects=DAMPING + DAMPING), "effects[1].kind = 'damping' appears twice"),
    (
        "gravity-without-mass",
        scene(body=TENSOR, effects=effect('kind = "gravity"\npivot = [0.0, 0.0, -1.0]')),
        "effects[0].mass is required",
    ),
    (
        "gravity-no-pivot",
        scene(effects=effect('kind = "gravity"')),
        "gravity needs exactly one of 'pivot_to_com' or 'pivot'",
    ),
    (
        "gravity-two-pivots",
        scene(effects=effect('kind = "gravity"\npivot = [0, 0, 0]\npivot_to_com = [0, 0, 1]')),
        "gravity needs exactly one of 'pivot_to_com' or 'pivot'",
    ),
    # --- huge and tiny numbers
    ("dt-denormal", scene(run='solver = "RKMK4"\ndt = 1e-320\nt1 = 1.0'), "is inf steps, more than a run may take"),
    ("t1-1e300", scene(run='solver = "RKMK4"\ndt = 0.01\nt1 = 1e300'), "is 1e+302 steps, more than a run may take"),
    ("t1-overflows", scene(run='solver = "RKMK4"\ndt = 0.01\nt1 = 1e400'), "run.t1 must be a finite number, got inf"),
    ("too-many-saved", scene(run='solver = "RKMK4"\ndt = 0.01\nt1 = 1e6'), "more than a run may save"),
    ("n-save-huge", scene(run=ADAPTIVE + "\nn_save = 1000000000000"), "run.n_save must be at most 10000000"),
    (
        "save-every-bigint",
        scene(run='solver = "RKMK4"\ndt = 0.01\nt1 = 1.0\nsave_every = 99999999999999999999999'),
        "run.save_every must be at most",
    ),
    ("max-steps-int64", scene(run=ADAPTIVE + "\nmax_steps = 9223372036854775807"), "run.max_steps must be at most"),
    (
        "momentum-overflows",
        scene(body='kind = "tensor"\ninertia = [1e300, 1e300, 1e300]', initial="omega = [1e300, 0.0, 0.0]"),
        "the initial momentum I omega overflows",
    ),
    (
        "inertia-underflows",
        scene(body='kind = "box"\nmass = 1e-300\nlx = 1e-5\nly = 1e-5\nlz = 1e-5'),
        "is singular or too small to invert",
    ),
    (
        "inertia-overflows",
        scene(body='kind = "cylinder"\nmass = 1.0\nradius = 1e200\nlength = 1.0'),
        "the inertia is not finite",
    ),
    (
        "pivot-far-away",
        scene(effects=effect('kind = "gravity"\npivot_to_com = [0.0, 0.0, 1e300]')),
        "body about the gravity pivot: the inertia is not finite",
    ),
    # --- not TOML
    ("toml-open-table", "[body\nkind = 'sphere'\n", "not valid TOML"),
    ("toml-duplicate-key", 'name = "a"\nname = "b"\n', "not valid TOML"),
    ("toml-duplicate-table", VALID + '[body]\nkind = "sphere"\n', "not valid TOML"),
    ("toml-unterminated-string", 'name = "corpus\n', "not valid TOML"),
    ("toml-unclosed-array", scene(initial="omega = [1.0, 0.0, 0.0"), "not valid TOML"),
    ("toml-no-key", "= 5\n", "not valid TOML"),
    ("toml-json", '{"body": {"kind": "tee_handle"}}', "not valid TOML"),
    ("latin-1", scene(top="name = 'café'").encode("latin-1"), "not valid TOML: not UTF-8 text (byte e9"),
    ("binary", bytes(range(256)), "not valid TOML"),
    ("utf-8-bom", b"\xef\xbb\xbf" + VALID.encode(), "not valid TOML"),
    ("nul-byte", VALID.encode().replace(b"corpus", b"cor\x00pus"), "not valid TOML"),
    # --- empty
    ("empty", "", "scene: missing required key 'body'"),
    ("only-comments", "# nothing here\n\n", "scene: missing required key 'body'"),
]

IDS = [c[0] for c in CORPUS]


def test_corpus_is_large_and_the_valid_base_loads():
    assert len(CORPUS) >= 60 and len(set(IDS)) == len(IDS)
    import lierk.app.scene

    lierk.app.scene.from_dict(__import__("tomllib").loads(VALID))
    lierk.app.scene.from_dict(__import__("tomllib").loads(scene(run=ADAPTIVE, effects=DAMPING)))


@pytest.fixture
def no_integration(monkeypatch):
    """Fail the test if a malformed scene gets as far as integrating."""
    calls = []

    def integrate(*args, **kwargs):
        calls.append(args)
        raise AssertionError("a malformed scene was integrated")

    monkeypatch.setattr(lierk.app.scene.Scene, "solve", integrate)
    return calls


def run(argv, capsys):
    try:
        code = cli.main([str(a) for a in argv])
    except SystemExit as e:  # argparse
        code = e.code
    except BaseException as e:  # would be a traceback from the console script
        pytest.fail(f"cli.main raised {type(e).__name__}: {e}")
    out, err = capsys.readouterr()
    return code, out, err


def check_one_line(code, out, err, fragment):
    assert code != 0
    lines = err.splitlines()
    assert len(lines) == 1 and err.endswith("\n"), err
    assert lines[0].startswith("lierk simulate: error: "), lines[0]
    assert fragment in lines[0], lines[0]
    assert "Traceback" not in out + err
    assert out == ""


@pytest.mark.parametrize("name, text, fragment", CORPUS, ids=IDS)
def test_malformed_scene_is_one_line(tmp_path, capsys, no_integration, name, text, fragment):
    path = tmp_path / f"{name}.toml"
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    code, out, err = run(["simulate", path, "--out", tmp_path / "out", "--no-gif"], capsys)
    check_one_line(code, out, err, fragment)
    assert code == 2  # a mistake in the scene, not a failed run
    assert not no_integration
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("what", ["directory", "missing", "unreadable"])
def test_scene_path_that_is_not_a_readable_file(tmp_path, capsys, no_integration, what):
    if what == "directory":
        path, fragment = tmp_path, "scene file is a directory"
    elif what == "missing":
        path, fragment = tmp_path / "nowhere" / "scene.toml", "scene file not found"
    else:
        path = tmp_path / "locked.toml"
        path.write_text(VALID)
        path.chmod(0)
        try:
            open(path).close()
            pytest.skip("running as a user who can read any file")
        except PermissionError:
            pass
        fragment = "cannot read the scene file"
    code, out, err = run(["simulate", path, "--out", tmp_path / "out"], capsys)
    check_one_line(code, out, err, fragment)
    assert not no_integration
