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
