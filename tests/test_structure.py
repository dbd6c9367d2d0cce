"""Package structure: module-level imports (``if TYPE_CHECKING:`` ones included) form a DAG, no
function-level imports of torchfmap modules (and of third-party ones only when optional), seeds
and descriptors import nothing from bases, modules stay short, one home per shared check, errors
in one module; the tests mirror the package (a few declared concept files aside)."""

from __future__ import annotations

import ast
import builtins
import re
import warnings
from pathlib import Path

import torchfmap

ROOT = Path(torchfmap.__file__).parent
#: Third-party modules that may be imported inside functions: optional dependencies only.
OPTIONAL_IMPORTS = {
    "matplotlib",
    "mpl_toolkits",
    "cholespy",
    "sksparse",
    "distributed",
    "pymeshlab",
    "plotly",
}
#: Most lines a module of torchfmap may have (docs/architecture.md rule 7: split at ~400).
MAX_MODULE_LINES = 450


def _module_name(path: Path) -> str:
    parts = ("torchfmap",) + path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def _sources() -> dict[str, tuple[Path, ast.Module]]:
    out = {}
    for path in sorted(ROOT.rglob("*.py")):
        out[_module_name(path)] = (path, ast.parse(path.read_text(encoding="utf-8"), str(path)))
    return out


SOURCES = _sources()


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    """Absolute name of the module a ``from ... import`` reads from."""
    if node.level == 0:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _imports(module: str, path: Path, tree: ast.Module, sources=None):
    """``(module-level, function-level)`` lists of ``(imported module, line)``; a ``from X import
    y`` where ``X.y`` is a module (one of ``sources``, default :data:`SOURCES`) counts as
    importing ``X.y`` too. Imports under ``if TYPE_CHECKING:`` count as module-level: they never
    run, but a cycle through them is still a cycle of the design (and breaks at run time as
    soon as someone turns the annotation into a real import)."""
    sources = SOURCES if sources is None else sources
    top, inner = [], []

    def targets(node) -> list[str]:
        if isinstance(node, ast.Import):
            return [alias.name for alias in node.names]
        base = _resolve(module, _is_package(path), node)
        names = [base]
        for alias in node.names:
            if f"{base}.{alias.name}" in sources:
                names.append(f"{base}.{alias.name}")
        return names

    def visit(node, in_function: bool) -> None:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            for name in targets(node):
                (inner if in_function else top).append((name, node.lineno))
            return
        nested = in_function or isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
        for child in ast.iter_child_nodes(node):
            visit(child, nested)

    for node in tree.body:
        visit(node, False)
    return top, inner


def _ancestors(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def import_graph(
    include_functions: bool = False, sources=None
) -> tuple[dict[str, set[str]], dict[str, list[tuple[str, int]]]]:
    """Module-level edges (``if TYPE_CHECKING:`` imports included) between torchfmap modules
    (with ``include_functions``, function-level ones too), and all function-level imports per
    module. ``sources``: ``{module: (path, tree)}``, default the package (:data:`SOURCES`).

    Importing ``a.b.c`` also runs the packages ``a`` and ``a.b``: those count as edges too,
    except packages that contain the importing module (they are already being imported).
    """
    sources = SOURCES if sources is None else sources
    graph: dict[str, set[str]] = {name: set() for name in sources}
    inner_all: dict[str, list[tuple[str, int]]] = {}
    for module, (path, tree) in sources.items():
        top, inner = _imports(module, path, tree, sources)
        inner_all[module] = inner
        own = set(_ancestors(module)) | ({module} if _is_package(path) else set())
        for name, _ in top + (inner if include_functions else []):
            if not name.startswith("torchfmap"):
                continue
            for target in [*_ancestors(name), name]:
                if target in sources and target not in own and target != module:
                    graph[module].add(target)
    return graph, inner_all


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state:
                found = dfs(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            found = dfs(node)
            if found:
                return found
    return None


def test_walker_sees_every_module_and_resolves_relative_imports():
    graph, _ = import_graph()
    assert {"torchfmap", "torchfmap._util.checks", "torchfmap.nn.data", "torchfmap.bases.basis"} <= set(graph)
    assert "torchfmap.errors" in graph["torchfmap.bases.basis"]  # from ..errors import ...
    assert "torchfmap.nn.functional" in graph["torchfmap.nn"]  # from . import functional
    assert "torchfmap.operators" in graph["torchfmap.seeds"]  # parent package of operators.heat runs too


def test_cycle_finder_reports_a_cycle():
    assert _find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _find_cycle({"a": {"b"}, "b": set()}) is None


def _synthetic(modules: dict[str, str]) -> dict[str, tuple[Path, ast.Module]]:
    """``{module: (path, tree)}`` of source texts, laid out as files under ROOT (never read)."""
    out = {}
    for name, text in modules.items():
        parts = name.split(".")[1:]
        path = ROOT.joinpath(*parts).with_suffix(".py") if parts else ROOT / "__init__.py"
        out[name] = (path, ast.parse(text))
    return out


def test_type_checking_imports_count_for_cycles():
    """A cycle closed only by an ``if TYPE_CHECKING:`` import is reported (e.g. the old
    ``bases.basis`` <-> ``bases.orthonormalize`` loop)."""
    sources = _synthetic(
        {
            "torchfmap": "",
            "torchfmap.a": "from .b import g\n",
            "torchfmap.b": (
                "from typing import TYPE_CHECKING\n"
                "if TYPE_CHECKING:\n    from .a import f\n"
                "if typing.TYPE_CHECKING:\n    import torchfmap.c\n"
            ),
            "torchfmap.c": "",
        }
    )
    graph, inner = import_graph(sources=sources)
    assert graph["torchfmap.b"] == {"torchfmap.a", "torchfmap.c"} and not inner["torchfmap.b"]
    assert _find_cycle(graph) == ["torchfmap.a", "torchfmap.b", "torchfmap.a"]


def test_seeds_and_descriptors_import_nothing_from_bases():
    """Seeds and descriptors come before bases in the data flow: the heat kernels they use live
    in ``operators.heat``."""
    graph, _ = import_graph(include_functions=True)
    for module in ("torchfmap.seeds", "torchfmap.descriptors"):
        bad = sorted(t for t in graph[module] if t == "torchfmap.bases" or t.startswith("torchfmap.bases."))
        assert not bad, f"{module} imports {bad}: import heat kernels from torchfmap.operators.heat"


def test_the_solver_and_the_bases_know_no_basis_kind():
    """Kinds sit above the functional-map layer (they build bases, and solve and refine maps by
    calling it with plain weights): nothing under ``bases``, ``fmap`` or ``operators`` imports
    ``torchfmap.kinds`` (the registry included), no registry lives under ``bases``, and no
    ``fmap`` module names the registry ``KINDS``, a kind class or reads a kind's settings."""
    graph, _ = import_graph(include_functions=True)
    below = [m for m in graph if m.split(".")[1:2] in (["bases"], ["fmap"], ["operators"])]
    assert "torchfmap.fmap.refine" in below and "torchfmap.fmap.defaults" in below
    assert "torchfmap.bases.registry" not in graph and not (ROOT / "bases" / "registry.py").exists()
    for module in below:
        bad = sorted(t for t in graph[module] if t == "torchfmap.kinds" or t.startswith("torchfmap.kinds."))
        assert not bad, f"{module} imports {bad}: a kind's behaviour belongs in torchfmap/kinds"
    for path in sorted((ROOT / "fmap").glob("*.py")):
        text = path.read_text(encoding="utf-8")
        words = ("KINDS", "BasisKind", "get_kind", "kind_of", "registry")
        for word in [rf"\b{w}\b" for w in words] + [r"\bkind\.\w"]:
            found = re.search(word, text)
            assert not found, f"fmap/{path.name} names {found[0]!r}: the fmap layer takes plain weights"


def test_the_core_does_not_import_the_experiments():
    """``torchfmap.experimental`` holds experiments outside the core API: no other module imports
    it, and its ``__init__`` imports none of its submodules (some need torch)."""
    graph, _ = import_graph(include_functions=True)
    for module, targets in graph.items():
        if module.startswith("torchfmap.experimental"):
            continue
        bad = sorted(t for t in targets if t.startswith("torchfmap.experimental"))
        assert not bad, f"{module} imports {bad}: the core does not depend on experiments"
    assert not graph.get("torchfmap.experimental"), graph.get("torchfmap.experimental")


def test_module_lengths_are_reported():
    """A module past ``MAX_MODULE_LINES`` is reported in the suite's output (a warning), not
    refused: modules are split by concept (docs/architecture.md rule 7), and length alone does
    not decide where code goes. The count itself must be readable for every module."""
    lengths = {
        module: len(path.read_text(encoding="utf-8").splitlines()) for module, (path, _) in SOURCES.items()
    }
    assert all(n > 0 for n in lengths.values())
    long = {m: n for m, n in lengths.items() if n > MAX_MODULE_LINES}
    if long:
        warnings.warn(
            f"modules over {MAX_MODULE_LINES} lines (is there a second concept to split off?): "
            + ", ".join(f"{m} ({n})" for m, n in sorted(long.items())),
            stacklevel=1,
        )


def test_module_level_imports_form_a_dag():
    graph, _ = import_graph()
    cycle = _find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_no_cycle_hidden_in_function_level_imports():
    graph, _ = import_graph(include_functions=True)
    cycle = _find_cycle(graph)
    assert cycle is None, "import cycle through function-level imports: " + " -> ".join(cycle)


#: The one lazy boundary: the command line imports the torch-based learning path only in the
#: commands that use it (torchfmap.cli.commands, run by torchfmap.cli), so that classical commands
#: start without torch.
LAZY_TORCH = {
    "torchfmap.cli.commands": ("torch", "torchfmap.nn"),
    "torchfmap.cli.train": ("torch", "torchfmap.nn"),
}


def test_no_function_level_import_of_torchfmap_modules():
    _, inner = import_graph()
    bad = [
        f"{module}:{line} imports {name}"
        for module, items in inner.items()
        for name, line in items
        if (name == "torchfmap" or name.startswith("torchfmap."))
        and not name.startswith(LAZY_TORCH.get(module, ("-",)))
    ]
    assert not bad, "function-level imports of torchfmap modules (move them to module level):\n" + "\n".join(
        bad
    )


def test_function_level_imports_only_of_optional_dependencies():
    _, inner = import_graph()
    bad = [
        f"{module}:{line} imports {name}"
        for module, items in inner.items()
        for name, line in items
        if not name.startswith("torchfmap")
        and name.split(".")[0] not in OPTIONAL_IMPORTS
        and not name.startswith(LAZY_TORCH.get(module, ("-",)))
    ]
    assert not bad, "function-level imports of required modules:\n" + "\n".join(bad)


def _definitions() -> dict[str, list[str]]:
    """Top-level function and class names -> modules defining them."""
    found: dict[str, list[str]] = {}
    for module, (_, tree) in SOURCES.items():
        for node in tree.body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                found.setdefault(node.name, []).append(module)
    return found


def test_classical_commands_and_import_do_not_import_torch():
    """``import torchfmap``, the CLI module and a feature-aware match (C = I, no solve) run
    without importing torch (it costs about two seconds); the functional-map solve shares its
    torch core with ``torchfmap.nn`` (one implementation), and the learning path imports it."""
    import subprocess
    import sys

    code = (
        "import sys, torchfmap, torchfmap.cli\n"
        "from torchfmap.data import demo_pair\n"
        "from torchfmap.evaluate.scores import gt_from_map, landmarks_from_gt\n"
        "x, y, g = demo_pair()\n"
        "torchfmap.match(x, y, landmarks=landmarks_from_gt(x, gt_from_map(g), 6), basis='diffusion', k=20)\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
        "import torchfmap.nn\n"
        "assert 'torch' in sys.modules\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]


def test_every_public_name_has_one_home():
    """No public function or class is defined in two modules (one implementation per concept;
    a helper shared by several modules lives in one of them, or in ``_util``), and the shared
    helpers are defined where the architecture says: the checks in ``_util.checks``."""
    twice = {
        name: mods for name, mods in _definitions().items() if len(mods) > 1 and not name.startswith("_")
    }
    assert not twice, f"defined in several modules: {twice}"
    assert _definitions()["check_vertex_indices"] == ["torchfmap._util.checks"]


def test_symmetry_is_checked_only_in_checks():
    pattern = re.compile(r"(\b\w+(?:\[\d\])?)\s*-\s*\1\.T\b")  # e.g. `L - L.T`, `ops[0] - ops[0].T`
    bad = [
        f"{path.relative_to(ROOT)}:{i}: {line.strip()}"
        for module, (path, _) in SOURCES.items()
        if module != "torchfmap._util.checks"
        for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if pattern.search(line)
    ]
    assert not bad, "symmetry checks outside torchfmap._util.checks (use is_symmetric/check_symmetric):\n" + (
        "\n".join(bad)
    )


def _base_names(node: ast.ClassDef) -> list[str]:
    names = []
    for base in node.bases:
        if isinstance(base, ast.Name):
            names.append(base.id)
        elif isinstance(base, ast.Attribute):
            names.append(base.attr)
    return names


def test_every_error_and_warning_class_lives_in_errors():
    classes = {}
    for module, (_, tree) in SOURCES.items():
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                classes.setdefault(node.name, []).append((module, _base_names(node)))
    exceptional = {n for n in dir(builtins) if n.endswith(("Error", "Exception", "Warning"))}
    exceptional.add("BaseException")
    changed = True
    while changed:  # classes deriving, directly or not, from an exception or warning
        changed = False
        for name, defs in classes.items():
            if name not in exceptional and any(set(b) & exceptional for _, b in defs):
                exceptional.add(name)
                changed = True
    misplaced = [
        f"{name} in {module}"
        for name, defs in classes.items()
        if name in exceptional
        for module, _ in defs
        if module != "torchfmap.errors"
    ]
    assert not misplaced, "exception/warning classes outside torchfmap.errors: " + ", ".join(misplaced)
    assert {"CorruptFileError", "NotPositiveDefiniteError", "MeshWarning"} <= exceptional


def test_public_error_names_still_importable():
    from torchfmap.errors import CorruptFileError, NotPositiveDefiniteError
    from torchfmap.operators import check_vertex_indices, lumped_diagonal
    from torchfmap.operators.laplacian import lumped_diagonal as lumped_from_laplacian
    from torchfmap.operators.solvers import NotPositiveDefiniteError as FromSolvers

    assert CorruptFileError.__module__ == "torchfmap.errors" and FromSolvers is NotPositiveDefiniteError
    assert lumped_diagonal is lumped_from_laplacian
    assert check_vertex_indices.__module__ == "torchfmap._util.checks"


def test_operator_numerics_live_in_operators_only():
    """One home per name: the bases package does not re-export the operators' numerics or the
    errors, and the pipeline module exports ``match`` alone (its steps live in their modules)."""
    import torchfmap.bases as bases
    import torchfmap.matching.pipeline as pipeline
    from torchfmap.operators import eigen, heat

    for name in ("heat_kernels", "heat_apply", "eigenpairs", "cf_poles", "fix_signs", "CorruptFileError"):
        assert name not in bases.__all__ and not hasattr(bases, name)
    assert pipeline.__all__ == ["match"]
    assert heat.heat_kernels.__module__ == "torchfmap.operators.heat"
    assert eigen.eigenpairs.__module__ == "torchfmap.operators.eigen"


#: Test files that check a concept across the package rather than one module: flat in ``tests/``,
#: each with the reason it is not a module's test file. Every other ``tests/**/test_*.py`` names
#: the module it tests (:func:`test_tests_mirror_the_package`).
CONCEPT_TESTS = {
    "test_structure.py": "the package's structure: the import DAG, lazy imports, module sizes, one home "
    "per shared helper, error classes in one module, and this layout of the tests",
    "test_docs_names.py": "README.md and docs/*.md against the code: every name they cite exists, and "
    "their checkable claims (counts, candidate lists, extras) hold",
    "test_readme.py": "the README's code blocks run as a reader would paste them",
    "test_api_coverage.py": "every public callable of every package is exercised by some test file",
    "test_bench.py": "the benchmark runner outside the package (python -m bench): each suite's smallest "
    "case in --quick mode on the demo pair, its settings and skips",
    "test_properties.py": "property-based runs (hypothesis) of random meshes through the eigenbasis, "
    "the diffusion basis, the solver, evaluation and save/load under one bounded example budget",
    "test_examples.py": "the numbered scripts of examples/ run on the demo pair and do what they promise",
    "test_fuzz.py": "every reader (meshes, index files, bases, checkpoints, cache entries) fed mutated "
    "files by bench/fuzz.py under one bounded example budget",
}
TESTS = Path(__file__).resolve().parent


def _stray_test_files(tests: Path, package: Path, concepts) -> list[str]:
    """Test files of ``tests`` that name no module of ``package`` and are not flat concepts.

    ``tests/a/test_b.py`` tests ``package/a/b.py`` (or the private ``a/_b.py``); ``tests/test_b.py``
    tests ``package/b.py``, ``package/_b.py`` or the package ``package/b/__init__.py``."""
    stray = []
    for path in sorted(tests.rglob("test_*.py")):
        rel = path.relative_to(tests)
        stem, home = rel.stem[len("test_") :], package.joinpath(*rel.parent.parts)
        homes = [home / f"{stem}.py", home / f"_{stem}.py"] + (
            [home / stem / "__init__.py"] if not rel.parent.parts else []
        )
        if not any(h.is_file() for h in homes) and not (not rel.parent.parts and rel.name in concepts):
            stray.append(rel.as_posix())
    return stray


def _folders_without_init(tests: Path) -> list[str]:
    return sorted(
        d.relative_to(tests).as_posix()
        for d in tests.rglob("*")
        if d.is_dir()
        and d.name != "__pycache__"
        and not any(part.startswith(".") for part in d.relative_to(tests).parts)
        and not (d / "__init__.py").is_file()
    )


def test_tests_mirror_the_package(tmp_path):
    """A test of ``torchfmap/<sub>/<module>.py`` lives in ``tests/<sub>/test_<module>.py`` (of a
    private ``_module.py`` in ``test_module.py``), of a top-level module or of a package's
    ``__init__`` in ``tests/test_<name>.py``; every other test file is one of the few declared
    :data:`CONCEPT_TESTS`; every folder of tests is a package (``__init__.py``), as ``tests/`` is."""
    # the checker on a made-up layout: it flags what it should
    pkg, tests = tmp_path / "pkg", tmp_path / "tests"
    for name in ("a/b.py", "a/_c.py", "d.py", "e/__init__.py"):
        (pkg / name).parent.mkdir(parents=True, exist_ok=True)
        (pkg / name).write_text("")
    for name in ("a/test_b.py", "a/test_c.py", "test_d.py", "test_e.py", "test_concept.py", "a/test_x.py"):
        (tests / name).parent.mkdir(parents=True, exist_ok=True)
        (tests / name).write_text("")
    (tests / "z").mkdir()
    assert _stray_test_files(tests, pkg, {"test_concept.py"}) == ["a/test_x.py"]
    assert _folders_without_init(tests) == ["a", "z"]
    # the real layout
    assert (TESTS / "__init__.py").is_file() and len(CONCEPT_TESTS) <= 8
    for name, why in CONCEPT_TESTS.items():
        assert (TESTS / name).is_file() and why, f"CONCEPT_TESTS names {name}, which is not a test file"
        assert _stray_test_files(TESTS, ROOT, {}).count(name) == 1, f"{name} names a module: not a concept"
    stray = _stray_test_files(TESTS, ROOT, CONCEPT_TESTS)
    assert not stray, (
        "test files that name no module of torchfmap (tests/<sub>/test_<module>.py for "
        f"torchfmap/<sub>/<module>.py) and are not declared in CONCEPT_TESTS: {stray}"
    )
    missing = _folders_without_init(TESTS)
    assert not missing, f"folders of tests without __init__.py (tests/ is a package): {missing}"


def _names_a_kind(annotation) -> bool:
    """A basis kind (:class:`~torchfmap.kinds.BasisKind` or a subclass) or its name (``str``), as a
    type or a string annotation."""
    from torchfmap.kinds.base import BasisKind

    if isinstance(annotation, type):
        return issubclass(annotation, (BasisKind, str))
    parts = {p.strip() for p in str(annotation).split("|")}
    kinds = {c.__name__ for c in BasisKind.__subclasses__()} | {"BasisKind", "str"}
    return bool(parts) and parts <= kinds | {"None"}


def test_kind_names_basis_kinds_only():
    """No public function, method or class takes a ``kind`` (or ``*_kind``) parameter but the
    basis-kind ones: a Laplacian has a ``scheme``, a column a ``family``, a mask, a shape
    difference's ``form``, a curvature ``measure``, a landmark descriptor a ``kernel``."""
    import importlib
    import inspect
    import pkgutil

    found: set = set()
    for info in pkgutil.walk_packages(torchfmap.__path__, "torchfmap."):
        if info.name.endswith("__main__"):
            continue
        module = importlib.import_module(info.name)
        for name, obj in list(vars(module).items()):
            if name.startswith("_") or getattr(obj, "__module__", None) != module.__name__:
                continue
            targets = [obj]
            if inspect.isclass(obj):
                methods = vars(obj).values()
                targets += [m for m in methods if inspect.isfunction(m) or isinstance(m, classmethod)]
            for target in targets:
                target = getattr(target, "__func__", target)
                try:
                    params = inspect.signature(target).parameters
                except (TypeError, ValueError):
                    continue
                for pname, param in params.items():
                    if pname == "kind" or pname.endswith("_kind") or pname.startswith("kind_"):
                        qual = f"{module.__name__}.{getattr(target, '__qualname__', name)}"
                        found.add((qual, param.annotation))
    assert found, "no basis-kind parameter found: the walk is broken"
    other = sorted(f for f, annotation in found if not _names_a_kind(annotation))
    assert not other, f"'kind' parameters not annotated as a basis kind (BasisKind, or its name str): {other}"
