"""The layering of the package (issue 21): import-linter's contracts in pyproject.toml, and no
import loop between modules or subpackages (imports inside functions counted), read with ast by
scripts/structure_targets.py."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _structure():
    path = ROOT / "scripts" / "structure_targets.py"
    spec = importlib.util.spec_from_file_location("structure_targets", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_import_linter_contracts_are_kept() -> None:
    lint = Path(sys.executable).with_name("lint-imports")
    p = subprocess.run([str(lint), "--no-cache"], cwd=ROOT, capture_output=True, text=True)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-2000:]
    assert "0 broken" in p.stdout


def test_no_import_loops_and_no_internal_imports_inside_functions() -> None:
    st = _structure()
    mods = st.modules()
    graph, inner = st.import_graph(mods)
    assert st.cycles(graph) == []
    sub: dict[str, set[str]] = {}
    for a, ts in graph.items():
        sa = st.subpackage(a)
        sub.setdefault(sa, set()).update(st.subpackage(b) for b in ts if st.subpackage(b) != sa)
    assert st.cycles(sub) == []
    assert inner == []


def test_the_loop_finder_finds_a_loop() -> None:
    st = _structure()
    assert st.cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert st.cycles({"a": {"b"}, "b": set()}) == []


def test_every_top_level_module_sits_in_a_layer() -> None:
    st = _structure()
    assert st.unlayered(st.modules()) == []


def test_no_near_duplicate_block_added() -> None:
    st = _structure()
    dups = st.near_duplicates(st.modules())
    assert len(dups) <= st.DUPLICATE_BUDGET, dups


def test_the_duplicate_finder_finds_a_renamed_copy(tmp_path: Path) -> None:
    st = _structure()
    body = ("def {f}(a, b):\n    c = a + b * 2\n    d = c - a / 3\n    e = d * c + 1\n"
            "    g = e - d * 4\n    h = g + e / 5\n    return h * g - 6\n")
    (tmp_path / "one.py").write_text(body.format(f="first"))
    (tmp_path / "two.py").write_text(body.format(f="second").replace("c", "cc").replace("2", "7"))
    (tmp_path / "three.py").write_text("def third(a):\n    return a\n")
    mods = {p.stem: p for p in sorted(tmp_path.glob("*.py"))}
    found = st.near_duplicates(mods)
    assert len(found) == 1 and {found[0][0], found[0][2]} == {"one", "two"}


def test_the_unlayered_finder_reads_the_contract() -> None:
    st = _structure()
    mods = dict(st.modules())
    mods["gt3dkit.brand_new"] = ROOT / "gt3dkit" / "cli.py"
    assert st.unlayered(mods) == ["gt3dkit.brand_new"]


def test_a_late_import_by_name_counts_outside_the_entry_point(tmp_path: Path) -> None:
    """``importlib.import_module("gt3dkit...")`` is an import: an edge of the graph, and inside a
    function an internal import inside a function, except in the modules allowed to load late
    (the package's lazy names, the light entry point)."""
    st = _structure()
    body = "import importlib\n\n\ndef f():\n    return importlib.import_module('gt3dkit.api')\n"
    (tmp_path / "gt3dkit").mkdir()
    for name in ("cli", "other", "api"):
        (tmp_path / "gt3dkit" / f"{name}.py").write_text(body)
    mods = {f"gt3dkit.{p.stem}": p for p in sorted((tmp_path / "gt3dkit").glob("*.py"))}
    graph, inner = st.import_graph(mods)
    assert graph["gt3dkit.other"] == {"gt3dkit.api"} and graph["gt3dkit.cli"] == {"gt3dkit.api"}
    assert [(m, t) for m, _, t in inner] == [("gt3dkit.other", "gt3dkit.api")]
