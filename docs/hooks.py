"""mkdocs hooks: the pages generated from the repository.

- The benchmarks guide (``docs/guides/benchmarks.md``) holds the region
  ``<!-- benchmark-results -->`` ... ``<!-- /benchmark-results -->``; at
  build time it is replaced by every file of ``benchmarks/results/`` (and
  ``benchmarks/results/h100/``) as the benchmark scripts last wrote them,
  each under a heading with a sentence on what it measures, and the figures
  are copied into the site.  In a clone the region holds a pointer to the
  files themselves.
- The scenes guide holds ``<!-- scene-schema -->`` ... ``<!-- /scene-schema -->``,
  a table of every key of a scene file, from the schema's own declarations
  (`lierk.app.scene_schema`: each table's fields, types and defaults, and
  the meanings its docstring gives them), and ``<!-- cli-help -->`` ...
  ``<!-- /cli-help -->``, the ``--help`` of ``lierk`` and each of its
  commands, from the parser itself (`lierk.app.cli_arguments.build_parser`).
  These two are committed, so that the page reads whole in a clone and on
  GitHub; ``python docs/hooks.py`` writes them again, ``tests/test_docs.py``
  checks that they match their sources, and the build fills them afresh.
- Figures of ``benchmarks/results/`` are linked from the guides by their
  path in the repository (``../../benchmarks/results/x.png`` from
  ``docs/guides/``), which resolves in a clone; the build points the links
  at the site's copy.

Nothing has to run before ``mkdocs build``: everything is read at build
time.  `render_results`, `render_scene_schema` and `render_cli_help` are
plain functions so that ``tests/test_docs.py`` can check what they produce.
"""

from __future__ import annotations

import ast
import contextlib
import inspect
import io
import json
import os
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
RESULTS_MARKER = "<!-- benchmark-results -->"
CLI_MARKER = "<!-- cli-help -->"
SCHEMA_MARKER = "<!-- scene-schema -->"

# What each result file measures, in the order the page shows them.  A file
# not listed here still appears (after these), with a generic sentence.
DESCRIPTIONS: dict[str, tuple[str, str]] = {
    "convergence": (
        "Convergence order",
        "The fitted order of every fixed-step solver on the T-handle, against the exact solution.",
    ),
    "work_precision": (
        "Work against precision, free body",
        "Time for 1000 near-axis T-handles to reach each error, lierk beside diffrax, MuJoCo, "
        "SciPy and the report's NumPy loop.",
    ),
    "torqued": (
        "Work against precision, torqued bodies",
        "The same for five families under torques (Lagrange tops, an asymmetric heavy top, a damped "
        "satellite, a spacecraft in orbit), lierk's best over the best peer.",
    ),
    "formulation": (
        "Torque-free formulations",
        "FreeRigidBody (body momentum as state) against SpatialFreeRigidBody (the report's form): "
        "error and speed at equal settings.",
    ),
    "tolerance_scope": (
        "What rtol means, by body family",
        "Global error over rtol, estimate over error and target_error's outcome on families "
        "beyond the calibration set.",
    ),
    "error_estimate": (
        "Global error estimate and accuracy on request",
        "How close estimate_error=True is to the true error, and what target_error costs.",
    ),
    "events": (
        "Event times against cost",
        "How accurately and how cheaply lierk and diffrax find an event time on fast Lagrange tops.",
    ),
    "event_cost": (
        "What an event costs",
        "The same solve with and without an event, one body and a vmap of 500, fixed RKMK4 and "
        "adaptive DOP853: compile and first call, and later runs.",
    ),
    "sensitivity": (
        "Jacobians against cost",
        "dR(T)/d omega0 for lierk's two methods and diffrax's adjoints, error against time.",
    ),
    "throughput": ("Throughput", "Body-steps per second of every fixed-step solver under jit(vmap), batch 1 to 10000."),
    "sweep": (
        "Sweeps at scale",
        "lierk.sweep against a held jit and native structure-of-arrays kernels in C and numba.",
    ),
    "sweep-cache-blocks": (
        "Sweeps in cache blocks",
        "lierk.sweep stepping each device's rows in blocks that fit the cache, against a plain jit(vmap) "
        "and one block per device (benchmarks/sweep.py --only cache-blocks).",
    ),
    "throughput-narrowed": (
        "Throughput, a narrowed run",
        "Selected solvers and batches of benchmarks/throughput.py, through jit(vmap) and through lierk.sweep.",
    ),
    "xla_soa": ("The XLA ceiling", "RKMK4 written per component inside XLA: how fast code that XLA generates can be."),
    "long_horizon": ("Long horizon, free T-handle", "Error and invariant drift of every solver over 1000 s."),
    "long_horizon_top": (
        "Long horizon, heavy tops",
        "Energy and Casimirs over 10^6 steps: the splittings' bounded energy against the Runge-Kutta methods' drift.",
    ),
    "long_horizon_brouwer": (
        "Long horizon, rounding",
        "Whether the energy error over 10^6 steps is a random walk (Brouwer's law) or a drift.",
    ),
    "first_result": (
        "Time to first result",
        "A fresh process's first solve and first Jacobian (trace, compile, run), lierk beside diffrax.",
    ),
    "first_result-jacfwd-eager": (
        "Time to first Jacobian, jitted and eager",
        "A later run of the first Jacobians alone: jax.jit(jax.jacfwd(f)) and an eager "
        "jax.jacfwd(f), as most code calls it, lierk beside diffrax.",
    ),
    "first_result-solve-jacfwd": (
        "Time to first solve and first Jacobian, a later run",
        "The first solves and first jax.jit(jax.jacfwd(f)) alone, after one body's "
        "adaptive step was written in fewer XLA kernels, lierk beside diffrax.",
    ),
    "first_result-call-jacfwd-eager-sensitivity": (
        "Time to first result from Python",
        "lierk.solve and lierk.sensitivity called from Python (lierk's own "
        "programs, compiled with lierk.one_body_compiler_options), an eager "
        "jax.jacfwd and jax.jit(jax.jacfwd(f)), lierk beside diffrax.",
    ),
    "first_result-solve": (
        "Time to first solve inside jax.jit, and its run",
        "jax.jit of one body's solve, lierk (the stage loop of the long tableaux) and with "
        "compact=False (the stages unrolled) beside diffrax: the first call in a fresh process "
        "and the compiled program's later runs.",
    ),
    "first_result-call": (
        "Time to first solve from Python, and later calls",
        "lierk.solve called from Python (one body's program, compiled for the CPU with "
        "lierk.one_body_compiler_options and the long tableaux' stage loop) beside diffrax's "
        "diffeqsolve: the first call in a fresh process and 20 later calls.",
    ),
    "compiler_options": (
        "A first call inside your own jax.jit, with lierk's compile options",
        "jax.jit(f) against jax.jit(f, compiler_options=lierk.one_body_compiler_options()) for "
        "one body's adaptive solve and its Jacobian, diffrax's jax.jit(f) beside them: the first "
        "call in a fresh process and the compiled program's later runs.",
    ),
    "compile_time": ("Compilation time", "What one program costs to trace and compile, lierk beside diffrax."),
    "latency": (
        "The command line, cold and warm",
        "What each lierk command costs from the shell, with and without the compilation cache.",
    ),
    "process_spread": (
        "One program, several processes",
        "The same compiled program timed in several fresh processes: the two speeds.",
    ),
    "design": (
        "Gradients of design costs",
        "One jax.grad of the design examples' costs (a fleet's mean over jax.vmap, a slew's held commands) "
        "through lierk.solve_sampled, against one evaluation, with jax.jacfwd beside it.",
    ),
    "scene_overhead": ("Scenes cost nothing extra", "A scene without effects against FreeRigidBody solved directly."),
}
SUBFOLDERS = {
    "h100": (
        "On an H100 GPU",
        "Benchmarks run on one NVIDIA H100 (JAX's default backend there, jax 0.11.2; "
        "the native anchors of the sweep on the machine's 16 Intel Xeon cores): each file names "
        "its commit and device.",
    )
}


def _slug(name: str) -> str:
    return name.replace("_", "-")


def _demote(markdown: str, levels: int) -> str:
    """Headings down by ``levels`` (outside code fences); the first level-1
    heading (the file's title) is dropped: the page gives its own."""
    out, fenced, dropped = [], False, False
    for line in markdown.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
        elif not fenced and re.match(r"#{1,6} ", line):
            if line.startswith("# ") and not dropped:
                dropped = True
                continue
            line = "#" * levels + line
        out.append(line)
    return "\n".join(out).strip() + "\n"


def _script_sentence(name: str) -> str:
    """The first sentence of ``benchmarks/NAME.py``'s docstring (read, not
    imported), for a result file `DESCRIPTIONS` does not know."""
    script = ROOT / "benchmarks" / f"{name}.py"
    doc = ast.get_docstring(ast.parse(script.read_text())) if script.exists() else None
    if not doc:
        return "Written by the benchmark script of the same name."
    first = " ".join(doc.split("\n\n")[0].split()).split(". ")[0].rstrip(".")
    return first + "."


def result_files() -> list[Path]:
    """Every result to show: the markdown tables, and the JSON files that have
    none, in `DESCRIPTIONS` order, then the others, then each subfolder's."""

    def ordered(folder: Path) -> list[Path]:
        md = {p.stem: p for p in folder.glob("*.md")}
        js = {p.stem: p for p in folder.glob("*.json") if p.stem not in md}
        found = {**js, **md}
        names = [n for n in DESCRIPTIONS if n in found] + sorted(n for n in found if n not in DESCRIPTIONS)
        return [found[n] for n in names]

    files = ordered(RESULTS)
    for sub in sorted(p for p in RESULTS.iterdir() if p.is_dir()):
        files += ordered(sub)
    return files


def render_results(page_dir: str = "guides") -> str:
    """The markdown of every result file, each under a ``##`` heading (``###``
    in a subfolder's section) with the file's own headings pushed below it."""
    up = "../" * len(Path(page_dir).parts)
    parts: list[str] = []
    current_sub = None
    for path in result_files():
        rel = path.relative_to(RESULTS)
        sub = rel.parts[0] if len(rel.parts) > 1 else None
        if sub != current_sub:
            current_sub = sub
            title, sentence = SUBFOLDERS.get(sub, (f"`{sub}/`", "Results from another machine."))
            parts.append(f"## {title} (`{sub}/`) {{#{sub}}}\n\n{sentence}\n")
        title, sentence = DESCRIPTIONS.get(path.stem) or (
            path.stem.replace("_", " ").capitalize(),
            _script_sentence(path.stem),
        )
        anchor = _slug(f"{sub}-{path.stem}" if sub else path.stem)
        level = "###" if sub else "##"
        script = f"benchmarks/{path.stem.split('-')[0]}.py"  # first_result-jacfwd-eager: first_result.py --works
        source = f"`benchmarks/results/{rel.as_posix()}`"
        if (ROOT / script).exists():
            source += f", written by `{script}`"
        parts.append(
            f"{level} {title}{' (' + sub + ')' if sub else ''} {{#{anchor}}}\n\n{sentence} Source: {source}.\n"
        )
        if path.suffix == ".md":
            parts.append(_demote(path.read_text(encoding="utf-8"), 2 if sub else 1))
        else:
            text = json.dumps(json.loads(path.read_text(encoding="utf-8")), indent=1)
            parts.append(f"```json\n{text}\n```\n")
        png = path.with_suffix(".png")
        if png.exists():
            parts.append(f"![{path.stem}]({up}benchmarks/results/{rel.with_suffix('.png').as_posix()})\n")
    return "\n".join(parts)


def render_cli_help() -> str:
    """``lierk --help`` and each command's ``--help``, as the parser prints them."""
    import argparse

    from lierk.app.cli_arguments import build_parser

    parser = build_parser()
    commands = [
        name for action in parser._actions if isinstance(action, argparse._SubParsersAction) for name in action.choices
    ]
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"
    try:
        blocks = []
        for argv in ([], *([c] for c in commands)):
            out = io.StringIO()
            with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
                build_parser().parse_args([*argv, "--help"])
            title = " ".join(["lierk", *argv, "--help"])
            blocks.append(f"### `{title}`\n\n```text\n{out.getvalue().rstrip()}\n```\n")
        return "\n".join(blocks)
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old


# Where each table of the schema sits in a scene file, by the class name's ending.
_SCHEMA_PLACES = (
    ("SceneFile", "the file"),
    ("Initial", "[initial]"),
    ("Run", "[run]"),
    ("EventKeys", "[[events]], every kind"),
    ("Body", "[body]"),
    ("Part", "[[body.parts]]"),
    ("Effect", "[[effects]]"),
    ("Event", "[[events]]"),
)


def _attributes(doc: str) -> dict[str, str]:
    """``name: text`` entries of a Google-style ``Attributes:`` section."""
    out: dict[str, str] = {}
    lines = inspect.cleandoc(doc or "").splitlines()
    inside, name, indent = False, None, 0
    for line in lines:
        if line.strip() == "Attributes:":
            inside, indent = True, None
            continue
        if not inside:
            continue
        if not line.strip():
            continue
        depth = len(line) - len(line.lstrip())
        if indent is None:
            indent = depth
        if depth < indent:
            break
        m = re.match(r"\s*(\w+)(?: \([^)]*\))?: (.*)", line)
        if depth == indent and m:
            name = m.group(1)
            out[name] = m.group(2).strip()
        elif name:
            out[name] += " " + line.strip()
    return out


def _value_types(module) -> dict[str, str]:
    """The docstring under each module-level alias (``Positive = ...`` then
    a string), read from the source: Python keeps no such docstring."""
    tree = ast.parse(Path(module.__file__).read_text())
    out = {}
    for node, after in zip(tree.body, tree.body[1:]):
        if (
            isinstance(node, ast.Assign)
            and len(node.targets) == 1
            and isinstance(node.targets[0], ast.Name)
            and isinstance(after, ast.Expr)
            and isinstance(after.value, ast.Constant)
            and isinstance(after.value.value, str)
        ):
            out[node.targets[0].id] = " ".join(after.value.value.split())
    return out


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def render_scene_schema() -> str:
    """Every table of a scene file with its keys: type, default and meaning,
    from `lierk.app.scene_schema`'s Structs, in the order it declares them."""
    import msgspec

    from lierk.app import scene_schema as schema

    tables, aliases = [], []
    known = _value_types(schema)
    for name in schema.__all__:
        obj = getattr(schema, name)
        if inspect.isclass(obj) and issubclass(obj, msgspec.Struct):
            tables.append(obj)
        elif name in known:
            aliases.append((name, known[name]))
    parts = []
    for cls in tables:
        place = next((p for suffix, p in _SCHEMA_PLACES if cls.__name__.endswith(suffix)), cls.__name__)
        tag = cls.__struct_config__.tag
        kind = f' `kind = "{tag}"`' if isinstance(tag, str) and tag != cls.__name__ else ""
        doc = inspect.cleandoc(cls.__doc__ or "")
        summary = " ".join(doc.split("\n\n")[0].split())
        meanings: dict[str, str] = {}
        annotations: dict[str, str] = {}
        for base in reversed(cls.__mro__):  # a subclass's words override its bases'
            annotations.update(getattr(base, "__annotations__", {}))
            meanings.update({k: v for k, v in _attributes(base.__dict__.get("__doc__")).items() if v})
        rows = ["| key | type | default | meaning |", "|---|---|---|---|"]
        for field in msgspec.structs.fields(cls):
            if field.name == cls.__struct_config__.tag_field:
                continue
            kind_of = str(annotations.get(field.name, field.type)).replace(" | UnsetType", "")
            kind_of = re.sub(r"^Annotated\[(.*), Meta\(.*\)\]$", r"\1", kind_of)
            if field.required:
                default = "required"
            elif field.default is msgspec.UNSET:
                default = ""
            elif field.default is not msgspec.NODEFAULT:
                default = f"`{field.default!r}`"
            else:
                default = f"`{field.default_factory()!r}`"
            rows.append(
                f"| `{field.name}` | `{_cell(kind_of)}` | {_cell(default)} | {_cell(meanings.get(field.name, ''))} |"
            )
        parts.append(
            f"### `{place}`{kind} {{#schema-{_slug(cls.__name__.lower())}}}\n\n{summary}\n\n" + "\n".join(rows) + "\n"
        )
    if aliases:
        rows = ["| name | what it is |", "|---|---|"] + [f"| `{n}` | {_cell(t)} |" for n, t in aliases]
        parts.append("### Types and limits {#schema-value-types}\n\n" + "\n".join(rows) + "\n")
    return "\n".join(parts)


def on_files(files, config):
    """Copy the benchmark figures into the site, at ``benchmarks/results/...``."""
    from mkdocs.structure.files import File

    for png in sorted(RESULTS.rglob("*.png")):
        uri = png.relative_to(ROOT).as_posix()
        files.append(File.generated(config, uri, abs_src_path=str(png)))
    return files


def end_marker(marker: str) -> str:
    """``<!-- /name -->`` for ``<!-- name -->``."""
    return marker.replace("<!-- ", "<!-- /", 1)


def fill(markdown: str, marker: str, text: str) -> str:
    """``markdown`` with the region from ``marker`` to its `end_marker`
    (or the marker alone, where there is no end) holding ``text``."""
    end = end_marker(marker)
    start = markdown.index(marker)
    stop = markdown.find(end, start)
    stop = start + len(marker) if stop < 0 else stop + len(end)
    return markdown[:start] + f"{marker}\n\n{text.strip()}\n\n{end}" + markdown[stop:]


def region(markdown: str, marker: str) -> str:
    """What ``markdown`` holds between ``marker`` and its `end_marker`."""
    start = markdown.index(marker) + len(marker)
    return markdown[start : markdown.index(end_marker(marker), start)].strip()


# The committed regions: (page, marker, renderer).
COMMITTED = (
    ("guides/scenes-and-cli.md", SCHEMA_MARKER, "render_scene_schema"),
    ("guides/scenes-and-cli.md", CLI_MARKER, "render_cli_help"),
)


def write_committed() -> list[Path]:
    """Write the committed regions from their sources; returns the pages changed."""
    changed = []
    for page, marker, renderer in COMMITTED:
        path = ROOT / "docs" / page
        old = path.read_text(encoding="utf-8")
        new = fill(old, marker, globals()[renderer]())
        if new != old:
            path.write_text(new, encoding="utf-8")
            changed.append(path)
    return changed


def site_links(markdown: str, page_dir: str) -> str:
    """Links into ``benchmarks/results/`` by their path in the repository,
    pointed at the site's copy (one level less up: the site's root is
    ``docs/``)."""
    up = "../" * len(Path(page_dir).parts)
    return markdown.replace(f"](../{up}benchmarks/results/", f"]({up}benchmarks/results/")


def on_page_markdown(markdown, page, config, files):
    page_dir = str(Path(page.file.src_uri).parent)
    if RESULTS_MARKER in markdown:
        markdown = fill(markdown, RESULTS_MARKER, render_results(page_dir))
    if SCHEMA_MARKER in markdown:
        markdown = fill(markdown, SCHEMA_MARKER, render_scene_schema())
    if CLI_MARKER in markdown:
        markdown = fill(markdown, CLI_MARKER, render_cli_help())
    return site_links(markdown, page_dir)


if __name__ == "__main__":
    import sys

    sys.path.insert(0, str(ROOT))
    for path in write_committed():
        print(f"wrote {path.relative_to(ROOT)}")
