"""Layering: ``sword_jax`` imports neither ``sim`` nor ``train``; ``sword_jax.dit`` does not reach ``convert``;
``benchmarks/``, ``examples/`` and ``sim/`` import no entry point; an entry point imports no other ``train``
module but the process setup ``train.distributed``; no ``train/`` module exceeds 300 lines; command lines
live in ``train/`` only (no ``if __name__ == "__main__":`` in ``sword_jax/`` or ``sim/``).

The scan reads the source (every import statement, including those inside functions, and literal
``importlib.import_module`` / ``__import__`` names), so a lazy import cannot slip through.
"""

import ast
import functools
import json
import os
import subprocess
import sys

import pytest

from tests.conftest import REPO

LIBRARY = os.path.join(REPO, "sword_jax")
FORBIDDEN = ("sim", "train")  # packages the library must not import


def _module_name(path: str) -> str:
    rel = os.path.splitext(os.path.relpath(path, REPO))[0].split(os.sep)
    return ".".join(rel[:-1] if rel[-1] == "__init__" else rel)


def _imports(source: str, module: str, *, is_package: bool = False) -> list[tuple[int, str, str, bool]]:
    """``(line, imported module, attribute or "", inside a function)`` of every import in ``source``
    (relative ones resolved)."""
    package = module if is_package else module.rpartition(".")[0]
    tree = ast.parse(source)
    lazy = {id(n) for fn in ast.walk(tree) if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            for n in ast.walk(fn)}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name, "", id(node) in lazy) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parts = parts[: len(parts) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            found += [(node.lineno, base, alias.name, id(node) in lazy) for alias in node.names]
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            name = ast.unparse(node.func)
            if name in ("importlib.import_module", "import_module", "__import__") and isinstance(node.args[0].value, str):
                found.append((node.lineno, node.args[0].value, "", id(node) in lazy))
    return found


def _imports_fresh(items: tuple[tuple[str, str, bool], ...]) -> list[list[tuple[int, str, str, bool]]]:
    """:func:`_imports` of each ``(source, module, is_package)``, parsed in a fresh interpreter: CPython
    3.11's AST constructor can raise "recursion depth mismatch" depending on the caller's state
    (cpython gh-106905), which happened inside a pytest-xdist worker of the full suite."""
    code = ("import json, sys; from tests.test_layering import _imports; "
            "print(json.dumps([_imports(s, m, is_package=p) for s, m, p in json.load(sys.stdin)]))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, input=json.dumps(items), capture_output=True,
                         text=True, check=True)
    return [[tuple(x) for x in found] for found in json.loads(out.stdout)]


@functools.lru_cache(maxsize=None)
def _library_imports() -> dict[str, list[tuple[int, str, str, bool]]]:
    """Every library file's imports (one fresh interpreter for all of them)."""
    files = _library_files()
    items = tuple((_read(p), _module_name(p), p.endswith("__init__.py")) for p in files)
    return dict(zip(files, _imports_fresh(items)))


def _library_files() -> list[str]:
    return sorted(os.path.join(d, f) for d, _, files in os.walk(LIBRARY) for f in files if f.endswith(".py"))


def _read(path: str) -> str:
    with open(path) as f:
        return f.read()


def _forbidden(found: list[tuple[int, str, str, bool]]) -> list[str]:
    return [f"line {line}: {name}" for line, name, _, _ in found if name.split(".")[0] in FORBIDDEN]


def test_scan_sees_imports_inside_functions():
    source = "def f():\n    from sim.env import make_env\n    import train.grpo\n\nimport simple\n"
    found, relative = _imports_fresh(((source, "sword_jax.x", False),
                                      ("def f():\n    from ..convert import wan22_dit\n", "sword_jax.dit.action_dit",
                                       False)))
    assert _forbidden(found) == ["line 2: sim.env", "line 3: train.grpo"]
    assert relative == [(2, "sword_jax.convert", "wan22_dit", True)]


def test_library_imports_neither_sim_nor_train():
    files = _library_files()
    assert len(files) > 50, files  # the scan really walks the package
    offenders = {os.path.relpath(p, REPO): bad for p, found in _library_imports().items() if (bad := _forbidden(found))}
    assert not offenders, f"sword_jax must not import {FORBIDDEN}; pass the sim piece as an argument: {offenders}"


def _import_graph() -> dict[tuple[str, bool], set[tuple[str, bool]]]:
    """``(module, init only) -> {(sword_jax module, init only)}``: what importing a module (init only)
    or also calling its functions imports.

    An imported module may have any of its functions called, so all of its imports count; the
    packages above it only have their ``__init__`` run, so only their module-level imports count.
    """
    modules = {_module_name(p): p for p in _library_files()}
    graph = {}
    for module, path in modules.items():
        edges = {True: set(), False: set()}
        for _, name, attr, lazy in _library_imports()[path]:
            target = f"{name}.{attr}" if f"{name}.{attr}" in modules else name
            parts = target.split(".")
            found = {(".".join(parts[:i]), True) for i in range(1, len(parts))} | {(target, False)}
            found = {(m, init_only) for m, init_only in found if m in modules and m != module}
            edges[False] |= found
            if not lazy:
                edges[True] |= found
        graph[(module, True)], graph[(module, False)] = edges[True], edges[False]
    return graph


def _reachable(graph: dict[tuple[str, bool], set[tuple[str, bool]]], start: str) -> set[str]:
    """Modules that importing ``start`` and calling its functions can import."""
    seen, todo = set(), [(start, False)]
    while todo:
        for nxt in graph[todo.pop()] - seen:
            seen.add(nxt)
            todo.append(nxt)
    return {m for m, _ in seen}


@pytest.mark.parametrize("package", ["sword_jax.dit"])
def test_dit_does_not_reach_convert(package):
    graph = _import_graph()
    assert "sword_jax.dit.model" in _reachable(graph, "sword_jax.convert.wan22_dit")  # convert -> dit is the way
    starts = [m for m, init_only in graph if not init_only and (m == package or m.startswith(package + "."))]
    assert len(starts) > 3, starts
    bad = {m: sorted(r for r in _reachable(graph, m) if r.startswith("sword_jax.convert")) for m in starts}
    assert not any(bad.values()), f"{package} must not import sword_jax.convert (converters import dit): {bad}"


def _package_edges() -> dict[str, set[str]]:
    """``subpackage -> {subpackages it imports}`` over every import of every library file (lazy ones too)."""
    subpackages = {d for d in os.listdir(LIBRARY) if os.path.isfile(os.path.join(LIBRARY, d, "__init__.py"))}
    edges: dict[str, set[str]] = {p: set() for p in subpackages}
    for path, found in _library_imports().items():
        source = _module_name(path).split(".")
        if len(source) < 2 or source[1] not in subpackages:
            continue
        for _, name, attr, _ in found:
            target = (name.split(".") + [attr])[1:2] if name.startswith("sword_jax") else []
            if target and target[0] in subpackages and target[0] != source[1]:
                edges[source[1]].add(target[0])
    return edges


def test_subpackages_import_each_other_one_way():
    edges = _package_edges()
    assert "dlb" in edges["world_model"] and "metrics" in edges["convert"], edges  # the scan sees arrows
    back = sorted((a, b) for a in edges for b in edges[a] if _reaches(edges, b, a))
    assert not back, f"subpackage imports that run back up (a cycle between packages): {back}"


def _reaches(edges: dict[str, set[str]], start: str, goal: str) -> bool:
    seen, todo = {start}, [start]
    while todo:
        for nxt in edges[todo.pop()] - seen:
            if nxt == goal:
                return True
            seen.add(nxt)
            todo.append(nxt)
    return False


def _files_under(folder: str) -> list[str]:
    return sorted(os.path.join(d, f) for d, _, files in os.walk(os.path.join(REPO, folder)) for f in files
                  if f.endswith(".py"))


@pytest.mark.parametrize("folder", ["benchmarks", "examples", "sim"])
def test_benchmarks_examples_and_sim_import_no_entry_point(folder):
    """They use the library, the simulators and the orchestration (``sword_jax.pipeline``); an entry point's
    work is reached through the orchestration or its command line, never by importing ``train``."""
    files = _files_under(folder)
    assert len(files) > 3, files
    found = _imports_fresh(tuple((_read(p), _module_name(p), p.endswith("__init__.py")) for p in files))
    offenders = {os.path.relpath(p, REPO): bad for p, imports in zip(files, found)
                 if (bad := [f"line {line}: {name}" for line, name, _, _ in imports if name.split(".")[0] == "train"])}
    assert not offenders, f"{folder}/ must not import train: {offenders}"


def test_train_modules_have_at_most_300_lines():
    files = [p for p in _files_under("train") if not p.endswith("__init__.py")]
    assert len(files) > 10, files
    too_long = {os.path.relpath(p, REPO): n for p in files if (n := len(_read(p).splitlines())) > 300}
    assert not too_long, f"train/ holds entry points of at most 300 lines (orchestration: sword_jax.pipeline): {too_long}"


PROCESS_SETUP = "train.distributed"  # the one train module the entry points share


def _train_modules_imported(found: list[tuple[int, str, str, bool]]) -> list[tuple[int, str]]:
    """``(line, train module)`` of every import of a ``train`` module (``from train import x`` names ``train.x``)."""
    out = []
    for line, name, attr, _ in found:
        if name == "train":
            out.append((line, f"train.{attr}" if attr else "train"))
        elif name.startswith("train."):
            out.append((line, name))
    return out


def test_scan_names_the_train_modules_an_entry_point_imports():
    source = ("from train import distributed, grpo\nimport train.pipeline\n"
              "def f():\n    from train.train_vae import run\n    from train.distributed import initialize\n")
    (found,) = _imports_fresh(((source, "train.x", False),))
    assert _train_modules_imported(found) == [(1, "train.distributed"), (1, "train.grpo"), (2, "train.pipeline"),
                                              (4, "train.train_vae"), (5, "train.distributed")]


def test_entry_points_import_no_other_entry_point():
    """Each ``train/`` module is an entry point: it parses a command line and calls the orchestration
    (``sword_jax.pipeline``, or ``sim`` where the simulator is needed); what two entry points share lives
    there, never in one of them. The process setup (``train.distributed``) is the one exception."""
    files = [p for p in _files_under("train") if not p.endswith("__init__.py")]
    assert len(files) > 10, files
    found = _imports_fresh(tuple((_read(p), _module_name(p), False) for p in files))
    edges = {os.path.relpath(p, REPO): _train_modules_imported(imports) for p, imports in zip(files, found)}
    assert any(m == PROCESS_SETUP for imported in edges.values() for _, m in imported), edges  # the scan sees them
    offenders = {path: [f"line {line}: {m}" for line, m in imported if m != PROCESS_SETUP]
                 for path, imported in edges.items()}
    offenders = {path: bad for path, bad in offenders.items() if bad}
    assert not offenders, (f"train/ modules import no other train module but {PROCESS_SETUP}; call the "
                           f"orchestration (sword_jax.pipeline, or sim/ where the simulator is needed): {offenders}")


def _main_blocks(source: str) -> list[int]:
    """Lines of the ``if __name__ == "__main__":`` tests in ``source`` (at any depth, either operand order)."""
    lines = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.If) and isinstance(node.test, ast.Compare):
            operands = [node.test.left, *node.test.comparators]
            names = {o.id for o in operands if isinstance(o, ast.Name)}
            constants = {o.value for o in operands if isinstance(o, ast.Constant)}
            if "__name__" in names and "__main__" in constants:
                lines.append(node.lineno)
    return lines


def _main_blocks_fresh(sources: tuple[str, ...]) -> list[list[int]]:
    """:func:`_main_blocks` of each source, parsed in a fresh interpreter (see :func:`_imports_fresh`)."""
    code = ("import json, sys; from tests.test_layering import _main_blocks; "
            "print(json.dumps([_main_blocks(s) for s in json.load(sys.stdin)]))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, input=json.dumps(sources), capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout)


def test_scan_finds_main_blocks():
    source = ('"""Run with:\n\n    if __name__ == "__main__":\n        main()\n"""\n'  # a docstring is no block
              'if "__main__" == __name__:\n    pass\n'
              'def f():\n    if __name__ == "__main__":\n        f()\n'
              'if __name__ == "x":\n    pass\n')
    assert _main_blocks_fresh((source, "x = 1\n")) == [[6, 9], []]


@pytest.mark.parametrize("folder", ["sword_jax", "sim"])
def test_library_and_sim_have_no_command_line(folder):
    """A command line is a thin entry point in ``train/`` (``main(argv)`` calling the library); a library
    module has none, so ``python -m sword_jax.<module>`` runs nothing."""
    files = _files_under(folder)
    assert len(files) > 20, files
    found = _main_blocks_fresh(tuple(_read(p) for p in files))
    offenders = {os.path.relpath(p, REPO): lines for p, lines in zip(files, found) if lines}
    assert not offenders, (f"{folder}/ has no `if __name__ == \"__main__\":` block (line numbers below); move "
                           f"the command line to an entry point in train/: {offenders}")
