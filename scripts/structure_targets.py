"""Issue 21 targets, measured by reading the package with :mod:`ast` (nothing is imported):

    python scripts/structure_targets.py [--list]

* **import loops** between modules and between subpackages, every ``import`` statement of
  gt3dkit's own modules counted wherever it stands (module level, inside a function, under
  ``if TYPE_CHECKING``): strongly connected components of the import graph (Tarjan);
  ``from pkg import mod`` counts as an import of ``pkg.mod``; a subpackage is the first name
  below ``gt3dkit`` (``fusion``, ``io``, ..., or a top-level module such as ``cli``);
* **imports inside functions** of gt3dkit's own modules (allowed only for heavy third-party
  libraries);
* **parameters**: every function with more than 10 (``self``/``cls`` not counted);
* **state-index literals** outside ``fusion/motion.py`` (``StateLayout``): in the estimation
  modules (``fusion/``), an integer literal 3, 6 or 9 used as a bound of a slice, an index, a
  ``range()`` argument or a comparison operand on a name that holds a state (``x``, ``X``,
  ``P``, ``x_*``, ``P_*``, ``xb*``, ``Pb*``, ``xj``, ``Pj``, ``dims``, ``i``/``k`` loops over state
  entries) -- a heuristic: it lists what it counts (``--list``);
* **cli.py** lines;
* issue 45's targets: **parameters typed ``Any``** (the annotation is exactly ``Any``) and
  **``dict[str, Any]``** written anywhere in the package (at most 10 each); **modules over 600
  lines** and **functions over 80 lines** (from ``def`` to the last line of the body, decorators
  and docstring included); **README.md lines** (at most 250); **top-level modules in no
  import-linter layer** (every ``gt3dkit.X`` of the package must be named by the ``layers``
  contract of ``pyproject.toml``); **near-duplicate blocks**: pairs of places sharing six or more
  consecutive lines of the same shape (identifiers, numbers and strings replaced by their kind;
  blank lines, comments and docstrings left out; runs of field declarations and runs that cross
  into another definition not counted), at
  most ``DUPLICATE_BUDGET`` (the count when issue 45 began: no block added since).

Exit status 1 when a target is missed.
"""

from __future__ import annotations

import argparse
import ast
import io
import re
import sys
import tokenize
import tomllib
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "gt3dkit"
STATE_NAMES = ("x", "X", "P", "xj", "Pj", "xl", "Pl", "dims")
STATE_PREFIXES = ("x_", "P_", "xb", "Pb", "X_s")
STATE_INTS = {3, 6, 9}
MAX_PARAMS = 10
MAX_CLI_LINES = 300
MAX_ANY = 10
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80
MAX_README_LINES = 250
DUPLICATE_WINDOW = 6
#: near-duplicate pairs on main when issue 45 began (no block may be added)
DUPLICATE_BUDGET = 11
PYPROJECT = ROOT.parent / "pyproject.toml"
README = ROOT.parent / "README.md"


def modules(root: Path = ROOT) -> dict[str, Path]:
    out = {}
    for p in sorted(root.rglob("*.py")):
        parts = list(p.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _targets(node: ast.AST, mod: str, is_pkg: bool) -> list[str]:
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if isinstance(node, ast.ImportFrom):
        if node.level:
            base = mod.split(".") if is_pkg else mod.split(".")[:-1]
            base = base[: len(base) - (node.level - 1)]
            name = ".".join(base + ([node.module] if node.module else []))
        else:
            name = node.module or ""
        return [name] + [f"{name}.{a.name}" for a in node.names]
    return []


class _Imports(ast.NodeVisitor):
    def __init__(self, mod: str, is_pkg: bool, known: set[str]) -> None:
        self.mod, self.is_pkg, self.known = mod, is_pkg, known
        self.depth = 0
        self.edges: set[str] = set()
        self.inner: list[tuple[int, str]] = []
        self.late: list[tuple[int, str]] = []

    def _func(self, node: ast.AST) -> None:
        self.depth += 1
        self.generic_visit(node)
        self.depth -= 1

    visit_FunctionDef = visit_AsyncFunctionDef = visit_Lambda = _func

    def _imp(self, node: ast.Import | ast.ImportFrom) -> None:
        own = {t for t in _targets(node, self.mod, self.is_pkg) if t in self.known and t != self.mod}
        self.edges |= own
        if own and self.depth:
            self.inner.append((node.lineno, sorted(own)[0]))

    visit_Import = visit_ImportFrom = _imp

    def visit_Call(self, node: ast.Call) -> None:
        """``importlib.import_module("gt3dkit...")`` (a name given as a literal): an edge like an
        import statement, and a late import wherever it stands (:data:`LATE_IMPORTERS`)."""
        f = node.func
        if (isinstance(f, ast.Attribute) and f.attr == "import_module" and node.args
                and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)
                and node.args[0].value in self.known and node.args[0].value != self.mod):
            self.edges.add(node.args[0].value)
            self.late.append((node.lineno, node.args[0].value))
        self.generic_visit(node)


#: The modules that import a gt3dkit module late, by name (``importlib.import_module``), and why:
#: the package's names from ``gt3dkit.api`` on first use (PEP 562), and ``gt3d``'s entry point,
#: which connects to a Dask scheduler before it loads the commands.
LATE_IMPORTERS = {"gt3dkit": "the package's lazy names", "gt3dkit.cli": "the entry point, light"}


def import_graph(mods: dict[str, Path]) -> tuple[dict[str, set[str]], list[tuple[str, int, str]]]:
    """Each module's imports of the package's modules (``importlib.import_module`` of a literal
    name included), and the internal imports inside functions: statements, and late imports by
    name outside :data:`LATE_IMPORTERS`."""
    known = set(mods)
    graph: dict[str, set[str]] = {}
    inner: list[tuple[str, int, str]] = []
    for m, p in mods.items():
        v = _Imports(m, p.name == "__init__.py", known)
        v.visit(ast.parse(p.read_text(), str(p)))
        graph[m] = v.edges
        inner += [(m, ln, t) for ln, t in v.inner]
        inner += [(m, ln, t) for ln, t in v.late if m not in LATE_IMPORTERS]
    return graph, inner


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    counter = 0
    nodes = sorted(set(graph) | {t for ts in graph.values() for t in ts})
    for start in nodes:
        if start in index:
            continue
        work = [(start, iter(sorted(graph.get(start, ()))))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on.add(start)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def subpackage(mod: str) -> str:
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def long_signatures(mods: dict[str, Path]) -> list[tuple[str, int, str, int]]:
    out = []
    for m, p in mods.items():
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                a = node.args
                names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs]
                names += [x.arg for x in (a.vararg, a.kwarg) if x is not None]
                names = [n for n in names if n not in ("self", "cls")]
                if len(names) > MAX_PARAMS:
                    out.append((m, node.lineno, node.name, len(names)))
    return out


def _is_state(node: ast.AST) -> bool:
    if isinstance(node, ast.Subscript):
        node = node.value
    if isinstance(node, ast.Attribute):
        node = ast.Name(node.attr)
    return isinstance(node, ast.Name) and (node.id in STATE_NAMES or node.id.startswith(STATE_PREFIXES))


def _int_lits(node: ast.AST) -> list[int]:
    return [n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and type(n.value) is int
            and n.value in STATE_INTS]


def state_literals(mods: dict[str, Path]) -> list[tuple[str, int, str]]:
    out = []
    for m, p in mods.items():
        if not m.startswith("gt3dkit.fusion.") or m == "gt3dkit.fusion.motion":
            continue
        for node in ast.walk(ast.parse(p.read_text())):
            hit = None
            if isinstance(node, ast.Subscript) and _is_state(node.value):
                sl = node.slice
                for s in (sl.elts if isinstance(sl, ast.Tuple) else [sl]):
                    if isinstance(s, ast.Slice) and any(b is not None and _int_lits(b)
                                                        for b in (s.lower, s.upper)):
                        hit = ast.unparse(node)
                    elif isinstance(s, ast.Constant | ast.BinOp) and _int_lits(s):
                        hit = ast.unparse(node)
            elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                  and node.func.id == "range" and node.args and _int_lits(node.args[-1] if len(node.args) < 3
                                                                         else node.args[1])
                  and all(isinstance(a, ast.Constant | ast.BinOp) for a in node.args)):
                hit = ast.unparse(node)
            elif isinstance(node, ast.Compare) and any(
                    isinstance(c, ast.Constant) and c.value in STATE_INTS and type(c.value) is int
                    for c in node.comparators) and isinstance(node.left, ast.Name) \
                    and node.left.id in ("i", "k", "j"):
                hit = ast.unparse(node)
            if hit:
                out.append((m, node.lineno, hit))
    return sorted(set(out))


def any_parameters(mods: dict[str, Path]) -> list[tuple[str, int, str]]:
    """Parameters annotated exactly ``Any`` (``self``/``cls`` never are)."""
    out = []
    for m, p in mods.items():
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                a = node.args
                for x in a.posonlyargs + a.args + a.kwonlyargs + [v for v in (a.vararg, a.kwarg) if v]:
                    if x.annotation is not None and ast.unparse(x.annotation) == "Any":
                        out.append((m, node.lineno, f"{node.name}({x.arg})"))
    return out


def dict_any(mods: dict[str, Path]) -> list[tuple[str, int]]:
    """Every ``dict[str, Any]`` written in the package (annotations, casts, aliases)."""
    return [(m, i + 1) for m, p in mods.items() for i, line in enumerate(p.read_text().splitlines())
            for _ in re.finditer(r"dict\[str,\s*Any\]", line)]


def long_modules(mods: dict[str, Path]) -> list[tuple[str, int]]:
    return [(m, n) for m, p in mods.items() if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES]


def long_functions(mods: dict[str, Path]) -> list[tuple[str, int, str, int]]:
    out = []
    for m, p in mods.items():
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                first = min([node.lineno] + [d.lineno for d in node.decorator_list])
                n = (node.end_lineno or node.lineno) - first + 1
                if n > MAX_FUNCTION_LINES:
                    out.append((m, node.lineno, node.name, n))
    return out


def unlayered(mods: dict[str, Path]) -> list[str]:
    """Top-level modules and subpackages of gt3dkit that the ``layers`` contract does not name."""
    conf = tomllib.loads(PYPROJECT.read_text())["tool"]["importlinter"]["contracts"]
    named = {name.strip() for c in conf if c.get("type") == "layers" for layer in c["layers"]
             for name in layer.split("|")}
    tops = {".".join(m.split(".")[:2]) for m in mods if m != "gt3dkit"}
    return sorted(t for t in tops if t not in named and not t.endswith("__main__"))


def _shapes(p: Path) -> list[tuple[int, str]]:
    """Each code line of ``p`` as ``(line number, its tokens' shape)``: names, numbers and strings
    by kind, docstrings, comments and the names of an import spread over lines left out."""
    src = p.read_text()
    doc_lines: set[int] = set()
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, ast.Import | ast.ImportFrom):  # its first line stays: windows skip it
            doc_lines.update(range(node.lineno + 1, (node.end_lineno or node.lineno) + 1))
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) \
                    and isinstance(first.value.value, str):
                doc_lines.update(range(first.lineno, (first.end_lineno or first.lineno) + 1))
    lines: dict[int, list[str]] = {}
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type in (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT,
                        tokenize.DEDENT, tokenize.ENDMARKER) or tok.start[0] in doc_lines:
            continue
        kind = {tokenize.NAME: "N", tokenize.NUMBER: "0", tokenize.STRING: "S"}.get(tok.type)
        if tok.type == tokenize.NAME and tok.string in KEYWORDS:
            kind = tok.string
        lines.setdefault(tok.start[0], []).append(kind or tok.string)
    return [(n, " ".join(t)) for n, t in sorted(lines.items())]


KEYWORDS = {"def", "class", "return", "if", "elif", "else", "for", "while", "in", "not", "and", "or",
            "is", "None", "True", "False", "with", "as", "try", "except", "finally", "raise", "import",
            "from", "lambda", "yield", "continue", "break", "pass", "del", "global", "assert"}


def near_duplicates(mods: dict[str, Path]) -> list[tuple[str, int, str, int]]:
    """Pairs of places whose ``DUPLICATE_WINDOW`` consecutive code lines have the same shape
    (overlapping windows of one pair counted once; windows of imports or of brackets alone are
    not counted)."""
    seen: dict[str, tuple[str, int]] = {}
    pairs: dict[tuple[str, str], tuple[str, int, str, int]] = {}
    last: dict[tuple[str, str], tuple[int, int]] = {}
    for m, p in mods.items():
        shapes = _shapes(p)
        for i in range(len(shapes) - DUPLICATE_WINDOW + 1):
            win = [s for _, s in shapes[i:i + DUPLICATE_WINDOW]]
            if sum(len(s.split()) > 3 for s in win) < DUPLICATE_WINDOW - 1 or any(
                    s.startswith(("import", "from")) for s in win) or all(
                    s.startswith("N :") for s in win) or any(  # a dataclass's fields
                    s.startswith(("def", "class", "@")) for s in win[1:]):  # across a definition
                continue
            key = "\n".join(win)
            here = (m, shapes[i][0])
            if key in seen and seen[key] != here:
                a, b = seen[key], here
                pk = (a[0], b[0])
                prev = last.get(pk)
                if prev is None or not (abs(a[1] - prev[0]) <= DUPLICATE_WINDOW
                                        and abs(b[1] - prev[1]) <= DUPLICATE_WINDOW):
                    pairs[(a[0] + str(a[1]), b[0] + str(b[1]))] = (a[0], a[1], b[0], b[1])
                last[pk] = (a[1], b[1])
            else:
                seen.setdefault(key, here)
    return list(pairs.values())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--list", action="store_true", help="list every finding")
    args = ap.parse_args(argv)
    mods = modules()
    graph, inner = import_graph(mods)
    mod_loops = cycles(graph)
    sub_graph: dict[str, set[str]] = defaultdict(set)
    for a, ts in graph.items():
        for b in ts:
            if subpackage(a) != subpackage(b):
                sub_graph[subpackage(a)].add(subpackage(b))
    sub_loops = cycles(sub_graph)
    sigs = long_signatures(mods)
    lits = state_literals(mods)
    cli_lines = len((ROOT / "cli.py").read_text().splitlines())
    anys, dicts = any_parameters(mods), dict_any(mods)
    big_mods, big_funcs = long_modules(mods), long_functions(mods)
    readme = len(README.read_text().splitlines())
    loose = unlayered(mods)
    dups = near_duplicates(mods)
    rows = [
        ("import loops between modules", sum(len(c) for c in mod_loops), len(mod_loops) == 0),
        ("import loops between subpackages", sum(len(c) for c in sub_loops), len(sub_loops) == 0),
        ("imports of gt3dkit inside functions", len(inner), len(inner) == 0),
        (f"functions over {MAX_PARAMS} parameters", len(sigs), not sigs),
        ("state-index literals outside StateLayout", len(lits), not lits),
        (f"cli.py lines (<= {MAX_CLI_LINES})", cli_lines, cli_lines <= MAX_CLI_LINES),
        (f"parameters typed Any (<= {MAX_ANY})", len(anys), len(anys) <= MAX_ANY),
        (f"dict[str, Any] written (<= {MAX_ANY})", len(dicts), len(dicts) <= MAX_ANY),
        (f"modules over {MAX_MODULE_LINES} lines", len(big_mods), not big_mods),
        (f"functions over {MAX_FUNCTION_LINES} lines", len(big_funcs), not big_funcs),
        (f"README.md lines (<= {MAX_README_LINES})", readme, readme <= MAX_README_LINES),
        ("top-level modules in no import-linter layer", len(loose), not loose),
        (f"near-duplicate blocks (<= {DUPLICATE_BUDGET})", len(dups), len(dups) <= DUPLICATE_BUDGET),
    ]
    print(f"package: {ROOT} ({len(mods)} modules)")
    for what, n, ok in rows:
        print(f"{what:<45} {n:>5}  {'PASS' if ok else 'FAIL'}")
    if args.list:
        for c in mod_loops:
            print("module loop:", " ".join(c))
        for c in sub_loops:
            print("subpackage loop:", " ".join(c))
        for m, ln, t in inner:
            print(f"inner import: {m}:{ln} -> {t}")
        for m, ln, name, k in sigs:
            print(f"parameters: {m}:{ln} {name} ({k})")
        for m, ln, s in lits:
            print(f"state literal: {m}:{ln} {s}")
        for m, ln, s in anys:
            print(f"Any parameter: {m}:{ln} {s}")
        for m, ln in dicts:
            print(f"dict[str, Any]: {m}:{ln}")
        for m, n in big_mods:
            print(f"long module: {m} ({n} lines)")
        for m, ln, name, n in big_funcs:
            print(f"long function: {m}:{ln} {name} ({n} lines)")
        for t in loose:
            print(f"no layer: {t}")
        for a, la, b, lb in dups:
            print(f"near-duplicate: {a}:{la} ~ {b}:{lb}")
    return 0 if all(ok for _, _, ok in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
