"""The public face: `import lierk` is the API, the application is `lierk.app`."""

import ast
import pathlib
import re
import subprocess
import sys

import pytest

import lierk

ROOT = pathlib.Path(lierk.__file__).parent

# What `lierk.app` imports from private modules: nothing.  The application
# is a client of `import lierk` (and its public namespaces) like any other.
KNOWN_PRIVATE: set = set()


def test_at_most_twelve_public_modules_sit_under_lierk():
    public = sorted(
        p.stem if p.is_file() else p.name
        for p in ROOT.iterdir()
        if not p.name.startswith(("_", ".")) and (p.suffix == ".py" or (p / "__init__.py").exists())
    )
    assert public == ["app", "checks", "conditions", "exact", "inertia", "so3", "tableaux"]
    assert len(public) <= 12


def test_import_lierk_loads_neither_the_application_nor_matplotlib_nor_tqdm():
    code = (
        "import sys, lierk; "
        "print(sorted(m for m in sys.modules "
        "if m.split('.')[0] in ('matplotlib', 'tqdm') or m.startswith('lierk.app')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_the_base_classes_a_user_extends_are_exported():
    for name in (
        "AbstractEffect",
        "AbstractProblem",
        "AbstractRigidBody",
        "AbstractSolver",
        "AbstractRKMK",
        "AbstractSplitting",
        "AbstractAdjoint",
        "AbstractStepController",
    ):
        cls = getattr(lierk, name)
        assert isinstance(cls, type) and cls.__name__ == name
    assert issubclass(lierk.Gravity, lierk.AbstractEffect)
    assert issubclass(lierk.Controller, lierk.AbstractStepController)
    assert issubclass(lierk.ForwardSensitivity, lierk.AbstractAdjoint)
    assert issubclass(lierk.DOP853, lierk.AbstractRKMK) and issubclass(lierk.AbstractRKMK, lierk.AbstractSolver)


@pytest.mark.parametrize(
    "old",
    [
        "lierk.fields",
        "lierk.effects",
        "lierk.body",
        "lierk.rigid_body",
        "lierk.solve",
        "lierk.loops",
        "lierk.scene",
        "lierk.cli",
    ],
)
def test_the_old_module_paths_are_gone(old):
    # `lierk.solve` is the function, not a module
    with pytest.raises(ModuleNotFoundError):
        __import__(old)


def _private_imports(path: pathlib.Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level == 2 and node.module:
                yield node.module.split(".")[0]
            elif node.level == 2:
                yield from (a.name for a in node.names)
            elif node.level == 0 and (node.module or "").startswith("lierk._"):
                yield node.module.split(".")[1]
            elif node.level == 0 and node.module == "lierk":
                yield from (a.name for a in node.names)
        elif isinstance(node, ast.Import):
            yield from (a.name.split(".")[1] for a in node.names if a.name.startswith("lierk._"))


def test_the_application_uses_only_the_public_api():
    found = {(p.stem, m) for p in (ROOT / "app").glob("*.py") for m in _private_imports(p) if m.startswith("_")}
    assert found <= KNOWN_PRIVATE, sorted(found - KNOWN_PRIVATE)
    # Nor does it read private names through the package.
    reads = {
        (p.stem, m)
        for p in (ROOT / "app").glob("*.py")
        for m in re.findall(
            r"\blierk\.(_\w+)",
            "\n".join(line for line in p.read_text().splitlines() if not line.lstrip().startswith("#")),
        )
    }
    assert not reads, sorted(reads)


def test_every_public_name_is_rendered_in_the_api_reference():
    text = "\n".join(p.read_text() for p in (ROOT.parent / "docs" / "api").glob("*.md"))
    documented = set(re.findall(r"^::: lierk\.(\w+)", text, re.M))
    missing = sorted(n for n in dir(lierk) if not n.startswith("_") and n != "app" and n not in documented)
    assert not missing, missing
