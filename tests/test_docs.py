"""The manual runs as written and says what it shows.

Every ```python block of README.md and of the docs site (``docs/**/*.md``)
runs, page by page: a page's blocks in order in one namespace, float64 on,
with the working directory a fresh temporary one.  A block preceded by the
line ``<!-- no-test -->`` is left out (a cluster launch, say); there are at
most a few.  A ```text block right after a python block is that block's
printed output: what the block prints must match it (the same words, the
numbers within 10%, or within a factor 10 where both are below 1e-6: errors
near rounding).  Every page with code asserts at least one of its claims in
its own code, and some pages' results are checked again here by name.

The ```sh blocks' ``lierk`` commands parse with the command line's own
parser and name scene files that exist; ``make`` commands name targets of
the Makefile.  The generated pages (benchmarks, the CLI reference) hold
what they are generated from.
"""

from __future__ import annotations

import ast
import contextlib
import importlib.util
import io
import math
import os
import re
import shlex
import shutil
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
NO_TEST = "<!-- no-test -->"
MAX_SKIPPED = 3


@dataclass
class Block:
    lang: str
    code: str
    line: int  # 1-based line of the opening fence
    end: int  # 0-based index of the closing fence
    skip: bool
    output: "Block | None" = None


_FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,})(?P<lang>[\w+-]*)")


def blocks(text: str) -> list[Block]:
    """The fenced code blocks of a markdown text, each ```python block with
    the ```text block that follows it (only blank lines between) as its
    output."""
    lines = text.splitlines()
    found: list[Block] = []
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, fence = len(m["indent"]), m["fence"]
        j, body = i + 1, []
        while j < len(lines) and lines[j].strip() != fence:
            line = lines[j]
            body.append(line[indent:] if not line[:indent].strip() else line.lstrip())
            j += 1
        before = [ln.strip() for ln in lines[:i] if ln.strip()]
        skip = bool(before) and before[-1] == NO_TEST
        found.append(Block(m["lang"], "\n".join(body) + "\n", i + 1, j, skip))
        i = j + 1
    for a, b in zip(found, found[1:]):
        between = lines[a.end + 1 : b.line - 1]
        if a.lang == "python" and b.lang == "text" and not any(ln.strip() for ln in between):
            a.output = b
    return found


def pages() -> list[Path]:
    return [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]


def _python_pages() -> list[Path]:
    return [p for p in pages() if any(b.lang == "python" for b in blocks(p.read_text()))]


def _id(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


# --- comparing printed output --------------------------------------------------

_NUMBER = re.compile(r"(?<![\w.])[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


def _close(a: float, b: float) -> bool:
    if a == b:
        return True
    if max(abs(a), abs(b)) < 1e-6:
        return a * b > 0 and abs(math.log10(abs(a) / abs(b))) <= 1
    return abs(a - b) <= 0.1 * max(abs(a), abs(b))


def output_mismatch(got: str, want: str) -> str | None:
    """None if ``got`` matches ``want`` (same text, numbers close), else why not."""

    def split(s):
        s = " ".join(s.split())
        return _NUMBER.sub("#", s), [float(x) for x in _NUMBER.findall(s)]

    (gt, gn), (wt, wn) = split(got), split(want)
    if gt != wt or len(gn) != len(wn):
        return f"the text differs:\n--- printed:\n{got}\n--- the page shows:\n{want}"
    bad = [(g, w) for g, w in zip(gn, wn) if not _close(g, w)]
    if bad:
        return f"numbers differ (printed, shown): {bad}\n--- printed:\n{got}\n--- the page shows:\n{want}"
    return None


def test_output_comparison_is_strict_enough():
    assert output_mismatch("ratio 1.02, 6000 steps\n", "ratio 1.1,  6000 steps") is None
    assert output_mismatch("ratio 1.3", "ratio 1.1") is not None
    assert output_mismatch("error 2e-13", "error 9e-14") is None  # rounding: within a factor 10
    assert output_mismatch("error 2e-12", "error 9e-14") is not None
    assert output_mismatch("6001 steps", "6000 steps") is None
    assert output_mismatch("7000 steps", "6000 steps") is not None
    assert output_mismatch("flip at 11.8 s", "flop at 11.8 s") is not None
    assert output_mismatch("(601, 3, 3)", "(601, 3)") is not None


def test_blocks_pair_code_with_its_output_and_see_the_skip_marker():
    text = "x\n\n```python\nprint(1)\n```\n\n```text\n1\n```\n\n<!-- no-test -->\n```python\nboom()\n```\n"
    a, b, c = blocks(text)
    assert a.lang == "python" and a.output is b and b.code == "1\n" and not a.skip
    assert c.skip and c.output is None


# --- the pages run -------------------------------------------------------------


def _asserts(code: str) -> int:
    """Assert statements and ``np.testing.assert_*`` calls in ``code``."""
    count = 0
    for node in ast.walk(ast.parse(code)):
        if isinstance(node, ast.Assert):
            count += 1
        elif isinstance(node, ast.Call):
            name = ast.unparse(node.func)
            count += name.split(".")[-1].startswith("assert_")
    return count


def run_page(path: Path, tmp_path: Path, monkeypatch) -> dict:
    """Run a page's python blocks in order in one namespace; check each
    block's printed output against the page.  Returns the namespace."""
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__main__"}
    # The pages are user code: JAX's default type promotion, as users have it.
    with jax.numpy_dtype_promotion("standard"):
        for block in blocks(path.read_text()):
            if block.lang != "python" or block.skip:
                continue
            where = f"{_id(path)}:{block.line}"
            out = io.StringIO()
            with contextlib.redirect_stdout(out):
                exec(compile(block.code, where, "exec"), namespace)
            if block.output is not None:
                problem = output_mismatch(out.getvalue(), block.output.code)
                assert problem is None, f"{where}: {problem}"
    return namespace


# Results checked by name, beyond the asserts in the pages' own code.
def _check_parameter_identification(ns):
    p_true, p_hat, sigma = (np.asarray(ns[k]) for k in ("p_true", "p_hat", "sigma"))
    assert np.all(np.abs(p_hat - p_true) < 3 * sigma), (p_hat - p_true) / sigma
    ratio = np.asarray(ns["scatter_ratio"])
    assert ratio.shape == (5,) and np.all((0.6 <= ratio) & (ratio <= 1.6)), ratio


def _check_readme(ns):
    # The README's quick start shows its claims as output; they are checked here
    # to the digits (tests/test_readme.py checks them again, with the rest of the README).
    found = ns["flips"].events
    times = np.asarray(found.ts[: int(found.count)])
    exact = float(ns["lierk"].exact.flip_interval(ns["body"].inertia, ns["body"].omega0))
    np.testing.assert_allclose(np.diff(times), exact, rtol=1e-9)
    assert float(ns["s"].jacobian_error) < 1e-8


def _check_t_handle(ns):
    flips = np.asarray(ns["flips"])
    np.testing.assert_allclose(np.diff(flips), float(ns["T_flip"]), rtol=1e-8)


def _check_heavy_top(ns):
    assert abs(float(ns["period"]) - 0.3536) < 5e-5 and abs(float(ns["precession_rate"]) - 6.247) < 5e-4


def _check_detumble(ns):
    assert float(ns["energy_ratio"]) > 100 and float(ns["final_rate"]) < 1e-6


def _check_optimal_slew(ns):
    # The independent DOP853 solve through the optimised commands arrives.
    assert float(ns["attitude_error"]) < 1e-6 and float(ns["final_rate"]) < 1e-8


def _check_tuned_controller(ns):
    (s_book, e_book), (s_tuned, e_tuned) = ns["results"]["textbook"], ns["results"]["tuned"]
    assert len(s_tuned) == 256 and s_tuned.mean() < 0.9 * s_book.mean() and e_tuned.mean() < 0.9 * e_book.mean()


CHECKS = {
    "README.md": _check_readme,
    "docs/examples/parameter-identification.md": _check_parameter_identification,
    "docs/examples/t-handle-flip.md": _check_t_handle,
    "docs/examples/heavy-top.md": _check_heavy_top,
    "docs/examples/detumble.md": _check_detumble,
    "docs/examples/optimal-slew.md": _check_optimal_slew,
    "docs/examples/tuned-controller.md": _check_tuned_controller,
}


# A page's own figures: ``![...](figures/NAME.png)``, drawn by its code.
_OWN_FIGURE = re.compile(r"!\[[^\]]*\]\(figures/([\w.-]+\.png)\)")


def check_figures(path: Path, drawn_in: Path) -> None:
    """Each figure a page shows from its ``figures/`` folder is one its code
    draws: the code saved a file of that name (in the working directory),
    of the committed figure's size.  With ``LIERK_WRITE_FIGURES=1`` the
    drawn figures replace the committed ones (to update them after a
    change: run the page's test, then commit ``docs/**/figures/``)."""
    import matplotlib.image

    for name in _OWN_FIGURE.findall(path.read_text()):
        drawn = drawn_in / name
        assert drawn.exists(), f"{_id(path)} shows figures/{name}, which its code did not save"
        committed = path.parent / "figures" / name
        if os.environ.get("LIERK_WRITE_FIGURES") == "1":
            committed.parent.mkdir(exist_ok=True)
            shutil.copyfile(drawn, committed)
        assert committed.exists(), f"{_id(path)}: figures/{name} is not committed (LIERK_WRITE_FIGURES=1 writes it)"
        assert matplotlib.image.imread(committed).shape == matplotlib.image.imread(drawn).shape, name


@pytest.mark.parametrize("path", _python_pages(), ids=_id)
def test_page_runs_and_checks_its_claims(path, tmp_path, monkeypatch):
    code = "".join(b.code for b in blocks(path.read_text()) if b.lang == "python" and not b.skip)
    assert _asserts(code) >= 1 or _id(path) in CHECKS, f"{_id(path)} asserts none of its claims"
    namespace = run_page(path, tmp_path, monkeypatch)
    check = CHECKS.get(_id(path))
    if check is not None:
        check(namespace)
    check_figures(path, tmp_path)


def test_every_image_resolves_from_its_markdown_file():
    """As a clone or GitHub shows the page: an image's path is relative to
    the markdown file (the site build points benchmark figures at its own
    copy, `docs/hooks.py`'s `site_links`)."""
    hooks = _hooks()
    seen = 0
    for path in pages():
        for link in re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", path.read_text()):
            if "://" in link:
                continue
            seen += 1
            assert (path.parent / link).exists(), f"{_id(path)}: {link} does not exist"
            if path.is_relative_to(DOCS) and "benchmarks/results/" in link:
                # On the site the file sits at the same path under docs/ (`on_files`).
                page_dir = path.parent.relative_to(DOCS).as_posix()
                site = hooks.site_links(f"]({link})", page_dir)[2:-1]
                real = (path.parent / link).resolve().relative_to(ROOT)
                assert (DOCS / page_dir / site).resolve().relative_to(DOCS.resolve()) == real, (link, site)
    assert seen >= 10, seen


def test_the_committed_generated_parts_match_their_sources():
    """The scene schema and the command reference are committed into the
    scenes guide, so that it reads whole without a build; they must be what
    the build would put there (``python docs/hooks.py`` rewrites them)."""
    hooks = _hooks()
    for page, marker, renderer in hooks.COMMITTED:
        text = (DOCS / page).read_text()
        assert hooks.region(text, marker) == getattr(hooks, renderer)().strip(), (
            f"docs/{page}: the part under {marker} is stale; run python docs/hooks.py"
        )


def test_the_checked_pages_exist_and_few_blocks_are_skipped():
    assert all((ROOT / page).exists() for page in CHECKS)
    skipped = [f"{_id(p)}:{b.line}" for p in pages() for b in blocks(p.read_text()) if b.skip]
    assert len(skipped) <= MAX_SKIPPED, skipped
    # Every page but the generated benchmarks page and the API reference runs some code.
    guides = [p for p in sorted((DOCS / "guides").glob("*.md")) if p.name != "benchmarks.md"]
    examples = sorted((DOCS / "examples").glob("*.md"))
    untested = [_id(p) for p in guides + examples if p not in _python_pages()]
    assert not untested, untested


# --- shell commands ------------------------------------------------------------


def _shell_commands():
    for path in pages():
        for block in blocks(path.read_text()):
            if block.lang not in ("sh", "bash", "console"):
                continue
            for raw in block.code.replace("\\\n", " ").splitlines():
                line = re.split(r" #| > | \| ", raw)[0].strip()  # no comment, redirection or pipe
                if line:
                    yield path, block, line


def test_lierk_commands_parse_and_make_targets_exist():
    from lierk.app.cli_arguments import build_parser

    targets = set(re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(), re.M))
    seen = {"lierk": 0, "make": 0}
    for path, block, line in _shell_commands():
        words = shlex.split(line)
        where = f"{_id(path)}:{block.line}: {line}"
        if words[0] == "make":
            seen["make"] += 1
            assert set(words[1:]) <= targets, where
        elif words[0] == "lierk":
            seen["lierk"] += 1
            args = build_parser().parse_args(words[1:])
            scene = getattr(args, "scene", None)
            assert scene is None or (ROOT / scene).exists(), where
    assert seen["lierk"] >= 5 and seen["make"] >= 3, seen


# --- generated pages -----------------------------------------------------------


def _hooks():
    spec = importlib.util.spec_from_file_location("docs_hooks", DOCS / "hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_benchmarks_page_is_generated_from_every_result_file():
    hooks = _hooks()
    page = (DOCS / "guides" / "benchmarks.md").read_text()
    assert hooks.RESULTS_MARKER in page
    text = hooks.render_results("guides")
    results = ROOT / "benchmarks" / "results"
    for md in results.rglob("*.md"):
        rel = md.relative_to(results)
        anchor = "-".join([*rel.parts[:-1], md.stem]).replace("_", "-")
        assert f"{{#{anchor}}}" in text, rel
        # The file's own tables, as the benchmark wrote them.
        first_row = next(line for line in md.read_text().splitlines() if line.startswith("|"))
        assert first_row in text, rel
    for png in results.rglob("*.png"):
        assert f"(../benchmarks/results/{png.relative_to(results).as_posix()})" in text
    # A result with JSON alone is shown too.
    assert "{#scene-overhead}" in text and '"scene_over_direct"' in text


def test_cli_reference_is_generated_from_the_parser():
    hooks = _hooks()
    assert hooks.CLI_MARKER in (DOCS / "guides" / "scenes-and-cli.md").read_text()
    text = hooks.render_cli_help()
    for command in ("simulate", "sweep", "accuracy", "schema"):
        assert f"usage: lierk {command}" in text
    assert "--target-error" in text and "--chunk-size" in text


def test_scene_schema_is_generated_from_the_schema_module():
    import msgspec

    from lierk.app import scene_schema

    hooks = _hooks()
    assert hooks.SCHEMA_MARKER in (DOCS / "guides" / "scenes-and-cli.md").read_text()
    text = hooks.render_scene_schema()
    structs = [
        getattr(scene_schema, n)
        for n in scene_schema.__all__
        if isinstance(getattr(scene_schema, n), type) and issubclass(getattr(scene_schema, n), msgspec.Struct)
    ]
    assert len(structs) >= 20
    for cls in structs:
        assert f"{{#schema-{cls.__name__.lower()}}}" in text, cls
        for field in msgspec.structs.fields(cls):
            if field.name != cls.__struct_config__.tag_field:
                assert f"| `{field.name}` |" in text, (cls, field.name)
    # Meanings come from the docstrings, inherited ones included.
    assert "| `save_every` | `Count` |" in text and "keep every k-th step" in text
    assert '`[[events]]` `kind = "tilt"`' in text and "| `terminate` | `Terminate` | `False` | true" in text


def test_every_page_is_in_the_nav_and_every_nav_entry_exists():
    config = (ROOT / "mkdocs.yml").read_text()
    in_nav = set(re.findall(r":\s*([\w/.-]+\.md)\s*$", config, re.M))
    on_disk = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md")}
    assert in_nav == on_disk, in_nav ^ on_disk
    assert "hooks:" in config and "docs/hooks.py" in config
