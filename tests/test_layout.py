"""The package layout's promises: no import cycles, hoidata never imports hoisdf, each package's layers, hoisdf on
hoidata's library layers only (never the build or its command line), files within the size budget.

Imports are read from the source (``ast``), lazy ones inside functions included, so a cycle hidden behind a
function-level import is still a cycle. ``from pkg import name`` counts as importing ``pkg.name`` when that
is a module, else ``pkg``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hoidata", "hoisdf")
MAX_LINES = 420  # "files under about 400 lines" (docs/development.md, "Style")


def _modules() -> dict[str, Path]:
    out = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    is_package = path.name == "__init__.py"
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative import
                anchor = name.split(".") if is_package else name.split(".")[:-1]
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names]
        else:
            continue
        for target in targets:
            while target and target not in modules:  # `import hoidata.hand.model` -> that module
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles():
    cycles = _cycles(_graph())
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_hoidata_never_imports_hoisdf():
    bad = {m: sorted(t for t in targets if t.split(".")[0] == "hoisdf")
           for m, targets in _graph().items() if m.split(".")[0] == "hoidata"}
    bad = {m: t for m, t in bad.items() if t}
    assert not bad, f"hoidata modules importing hoisdf: {bad}"


def test_files_stay_within_the_size_budget():
    long = {str(p.relative_to(ROOT)): n for p in _modules().values() if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"files over {MAX_LINES} lines: {long}"


# The recipes: each stands on the engine and records floors (their public names) and on the library layers, never on
# another recipe.
RECIPES = ("hoidata.build_sdf", "hoidata.render_synthetic", "hoidata.export", "hoidata.toy")
# hoidata's layers, bottom first: a module may import its own layer and the layers below, never one above, so the
# data flows one way (readers -> frames -> records -> shards; the toy writers and the CLI on top).
HOIDATA_LAYERS = (
    ("hoidata.errors", "hoidata.atomic", "hoidata.schema", "hoidata.sections", "hoidata.provenance",
     "hoidata.reading", "hoidata.reading_media", "hoidata.shapes"),
    ("hoidata.safe_pickle", "hoidata.geometry", "hoidata.store", "hoidata.render", "hoidata.cli_types"),
    ("hoidata.hand", "hoidata.objects", "hoidata.view"),  # view: a store's records with the MANO hand posed
    ("hoidata.datasets",),
    ("hoidata.engine",),
    ("hoidata.records",),
    ("hoidata.synth",),
    RECIPES,
    ("hoidata.cli", "hoidata.cli_defaults", "hoidata.cli_store", "hoidata.__main__"),
)


def _layer(module: str, layers=HOIDATA_LAYERS) -> int | None:
    """The layer of the longest prefix in ``layers`` that holds ``module`` (``hoisdf.training.losses`` before
    ``hoisdf.training``); a bare package name (``hoisdf``) holds only itself."""
    best = None
    for level, prefixes in enumerate(layers):
        for p in prefixes:
            inside = module == p or ("." in p and module.startswith(p + "."))
            if inside and (best is None or len(p) > best[0]):
                best = (len(p), level)
    return None if best is None else best[1]


def test_every_hoidata_module_has_a_layer():
    missing = [m for m in _modules() if m.startswith("hoidata.") and _layer(m) is None]
    assert not missing, f"hoidata modules in no layer of HOIDATA_LAYERS: {missing}"


def test_hoidata_imports_only_its_own_layer_and_below():
    up = {m: sorted(t for t in targets if t.startswith("hoidata.") and _layer(t) > _layer(m))
          for m, targets in _graph().items() if m.startswith("hoidata.")}
    up = {m: t for m, t in up.items() if t}
    assert not up, f"imports that run up a layer: {up}"


FLOORS = ("hoidata.engine", "hoidata.records")  # what the recipes stand on, bottom first


def _inside(module: str, prefixes) -> str | None:
    """The prefix of ``prefixes`` that holds ``module`` (itself or a module under it), else None."""
    return next((p for p in prefixes if module == p or module.startswith(p + ".")), None)


def _public(package: str) -> set[str]:
    """The names a package's ``__init__.py`` lists in ``__all__``."""
    tree = ast.parse((ROOT / package.replace(".", "/") / "__init__.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets):
            return set(ast.literal_eval(node.value))
    return set()


def _floor_problems(graph: dict[str, set[str]], public: dict[str, set[str]]) -> list[str]:
    """The floors' rules: the engine imports nothing of the records floor or a recipe, the records floor nothing of a
    recipe; a recipe imports no other recipe, and the floors only through their front doors (the package, or a
    module its ``__all__`` names: ``public``)."""
    problems = []
    for m, targets in sorted(graph.items()):
        for t in sorted(targets):
            if _inside(m, FLOORS[:1]) and (_inside(t, FLOORS[1:]) or _inside(t, RECIPES)):
                problems.append(f"the engine floor imports {t} ({m})")
            if _inside(m, FLOORS[1:]) and _inside(t, RECIPES):
                problems.append(f"the records floor imports the recipe {t} ({m})")
            mine, theirs, floor = _inside(m, RECIPES), _inside(t, RECIPES), _inside(t, FLOORS)
            if mine and theirs and mine != theirs:
                problems.append(f"the recipe {m} imports another recipe, {t}")
            if mine and floor and t != floor and t.rpartition(".")[2] not in public[floor]:
                problems.append(f"the recipe {m} imports {t}, not a public name of {floor}")
    return problems


def test_the_engine_and_records_are_floors_under_recipes_that_never_import_each_other():
    graph = _graph()
    assert set(RECIPES) <= {m for m in graph if _inside(m, RECIPES) == m}, "a recipe module or package is missing"
    problems = _floor_problems(graph, {floor: _public(floor) for floor in FLOORS})
    assert not problems, "; ".join(problems)


def test_the_floor_check_finds_each_kind_of_import():
    graph = {"hoidata.engine.launch": {"hoidata.records.worker"}, "hoidata.engine.pool": {"hoidata.build_sdf"},
             "hoidata.records.worker": {"hoidata.render_synthetic"},
             "hoidata.export.job": {"hoidata.build_sdf", "hoidata.engine", "hoidata.records.fingerprint"},
             "hoidata.toy.dexycb": {"hoidata.engine.engine", "hoidata.toy.scenes"}}
    assert _floor_problems(graph, {"hoidata.engine": set(), "hoidata.records": {"fingerprint"}}) == [
        "the engine floor imports hoidata.records.worker (hoidata.engine.launch)",
        "the engine floor imports hoidata.build_sdf (hoidata.engine.pool)",
        "the recipe hoidata.export.job imports another recipe, hoidata.build_sdf",
        "the records floor imports the recipe hoidata.render_synthetic (hoidata.records.worker)",
        "the recipe hoidata.toy.dexycb imports hoidata.engine.engine, not a public name of hoidata.engine"]


# hoisdf's layers, bottom first, the same rule: the scoring of result files (any method's; its own command
# ``hoisdf score`` included), which stands on nothing of the model; the network's parts; the data they eat; the
# settings (which gather the parts' settings dataclasses: the data's augmentation settings, the model's, the loss
# weights); training (the loss math, the trainer and checkpoints), which reads the settings; evaluation, which loads
# checkpoints; the command lines on top.
HOISDF_LAYERS = (
    ("hoisdf.scoring",),
    ("hoisdf", "hoisdf.model"),
    ("hoisdf.data",),
    ("hoisdf.config",),
    ("hoisdf.training",),
    ("hoisdf.evaluation",),
    ("hoisdf.train", "hoisdf.evaluate", "hoisdf.import_upstream", "hoisdf.ablation", "hoisdf.toy", "hoisdf.cli"),
)
# What hoisdf may import of hoidata: its library layers (prefixes), never the build (pipeline, export, synth, toy
# writers, render) nor its command line. hoisdf stands beside the build, not on it.
HOISDF_MAY_IMPORT = (
    "hoidata",  # the package itself (its version, where it lives): not its subpackages
    "hoidata.errors", "hoidata.atomic", "hoidata.schema", "hoidata.sections", "hoidata.provenance",
    "hoidata.reading", "hoidata.reading_media", "hoidata.shapes",  # the guarded door every file read goes through
    "hoidata.cli_types", "hoidata.safe_pickle", "hoidata.store", "hoidata.geometry", "hoidata.hand",
    "hoidata.objects",
    "hoidata.datasets.dexycb_layout",  # the DexYCB toolkit's file layout, for scoring its result files
    "hoidata.datasets.dexycb_frames",  # the toolkit's invalid-label marker (TOOLKIT_INVALID), for submissions
)
HOISDF_NEVER = ("hoidata.cli", "hoidata.__main__", "hoidata.engine", "hoidata.records", "hoidata.build_sdf",
                "hoidata.render_synthetic", "hoidata.export", "hoidata.synth",
                "hoidata.toy", "hoidata.render")


def test_every_hoisdf_module_has_a_layer():
    missing = [m for m in _modules() if m.split(".")[0] == "hoisdf" and _layer(m, HOISDF_LAYERS) is None]
    assert not missing, f"hoisdf modules in no layer of HOISDF_LAYERS: {missing}"


def test_hoisdf_imports_only_its_own_layer_and_below():
    up = {m: sorted(t for t in targets if t.split(".")[0] == "hoisdf"
                    and _layer(t, HOISDF_LAYERS) > _layer(m, HOISDF_LAYERS))
          for m, targets in _graph().items() if m.split(".")[0] == "hoisdf"}
    up = {m: t for m, t in up.items() if t}
    assert not up, f"imports that run up a layer: {up}"


def _hoisdf_problems(graph: dict[str, set[str]]) -> list[str]:
    """hoisdf's imports of hoidata outside :data:`HOISDF_MAY_IMPORT`, and every hoidata module of
    :data:`HOISDF_NEVER` that hoisdf reaches, directly or through the hoidata modules it imports."""
    allowed = [(p, p != "hoidata") for p in HOISDF_MAY_IMPORT]  # (prefix, whether its submodules count)
    problems, reached, todo = [], set(), []
    for m, targets in sorted(graph.items()):
        for t in sorted(targets):
            if m.split(".")[0] == "hoisdf" and t.split(".")[0] == "hoidata":
                if not any(t == p or (deep and t.startswith(p + ".")) for p, deep in allowed):
                    problems.append(f"{m} imports {t}, which is not on the allow-list")
                todo.append(t)
    while todo:
        t = todo.pop()
        if t not in reached:
            reached.add(t)
            todo.extend(graph.get(t, ()))
    problems += [f"hoisdf reaches {t}" for t in sorted(reached)
                 if any(t == p or t.startswith(p + ".") for p in HOISDF_NEVER)]
    return problems


def _foreign_imports(path: Path, lazy: bool = True) -> set[str]:
    """The top-level names of every module ``path`` imports; with ``lazy``, function-level imports included."""
    found = set()
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree) if lazy else tree.body:
        if isinstance(node, ast.Import):
            found.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module.split(".")[0])
    return found


# the scoring modules that drive the MANO layer themselves (ground-truth hands from a store's labels, HOT3D's MANO
# predictions): torch
# inside the function that does it, never at import
SCORING_POSES_MANO = ("hoisdf.scoring.recon_store", "hoisdf.scoring.score_hot3d", "hoisdf.scoring.score_arctic")


def _scoring_problems(graph: dict[str, set[str]], paths: dict[str, Path]) -> list[str]:
    """Ways the scoring floor (``hoisdf.scoring``) stands on the model: an import of a hoisdf module outside it
    (model, data, training, config, evaluation, the commands), or of torch itself (at import anywhere; inside a
    function outside :data:`SCORING_POSES_MANO`)."""
    problems = []
    for m in sorted(m for m in graph if m == "hoisdf.scoring" or m.startswith("hoisdf.scoring.")):
        problems += [f"{m} imports {t}" for t in sorted(graph[m])
                     if t.split(".")[0] == "hoisdf" and not t.startswith("hoisdf.scoring")]
        if "torch" in _foreign_imports(paths[m], lazy=m not in SCORING_POSES_MANO):
            problems.append(f"{m} imports torch")
    return problems


def test_the_scoring_floor_imports_no_model_code_and_no_torch():
    # a user who scores files reads hoisdf/scoring/ alone; torch is reached only through hoidata.hand (the MANO
    # layer: the wrist cap of ``hoisdf score contact``, the ground-truth hands of ``score recon --gt-store``, and
    # the joint orders)
    problems = _scoring_problems(_graph(), _modules())
    assert not problems, problems


def test_the_scoring_check_finds_a_model_import_and_a_lazy_torch(tmp_path):
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    a.write_text("from hoisdf.training.losses import hand_targets\n")
    b.write_text("def f():\n    import torch.nn\n    return torch\n")
    graph = {"hoisdf.scoring.a": {"hoisdf.training.losses", "hoisdf.scoring.b"}, "hoisdf.scoring.b": set(),
             "hoisdf.evaluation.x": {"hoisdf.model"}}
    paths = {"hoisdf.scoring.a": a, "hoisdf.scoring.b": b}
    assert _scoring_problems(graph, paths) == ["hoisdf.scoring.a imports hoisdf.training.losses",
                                               "hoisdf.scoring.b imports torch"]
    posing = tmp_path / "recon_store.py"
    posing.write_text("import numpy\n\n\ndef f():\n    import torch\n")
    assert _scoring_problems({"hoisdf.scoring.recon_store": set()}, {"hoisdf.scoring.recon_store": posing}) == []
    posing.write_text("import torch\n")
    assert _scoring_problems({"hoisdf.scoring.recon_store": set()}, {"hoisdf.scoring.recon_store": posing}) == [
        "hoisdf.scoring.recon_store imports torch"]


def test_hoisdf_imports_only_the_allowed_hoidata_layers_and_never_the_build_or_its_cli():
    problems = _hoisdf_problems(_graph())
    assert not problems, problems


def test_the_hoisdf_check_finds_a_cli_import_and_a_build_reached_through_a_library_module():
    graph = {"hoisdf.toy": {"hoidata.cli", "hoidata.cli_types"}, "hoisdf.train": {"hoidata.store"},
             "hoidata.cli": {"hoidata.build_sdf"}, "hoidata.cli_types": set(),
             "hoidata.store": {"hoidata.records.store_writer"}, "hoidata.build_sdf": set(),
             "hoidata.records.store_writer": set()}
    assert _hoisdf_problems(graph) == ["hoisdf.toy imports hoidata.cli, which is not on the allow-list",
                                       "hoisdf reaches hoidata.build_sdf", "hoisdf reaches hoidata.cli",
                                       "hoisdf reaches hoidata.records.store_writer"]


def _bench_problems(bench: Path) -> list[str]:
    """Ways a bench module breaks the bench rules: a bare import of a sibling, an import of another *script*
    (a module with a ``__main__`` block), or a change to ``sys.path``."""
    modules = {p.stem: p for p in bench.glob("*.py")}
    scripts = {name for name, p in modules.items() if 'if __name__ == "__main__"' in p.read_text()}
    problems = set()
    for name, path in sorted(modules.items()):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                targets = [node.module or ""] + [f"{node.module}.{alias.name}" for alias in node.names]
            else:
                targets = []
            for target in targets:
                head, _, rest = target.partition(".")
                if head in modules:
                    problems.add(f"{path.name} imports its sibling {head} by bare name")
                elif head == bench.name and rest.split(".")[0] in scripts:
                    problems.add(f"{path.name} imports the script {rest.split('.')[0]}")
            if isinstance(node, ast.Attribute) and node.attr == "path" and getattr(node.value, "id", None) == "sys":
                problems.add(f"{path.name} touches sys.path")
    return sorted(problems)


def test_bench_scripts_share_only_through_library_modules():
    assert not _bench_problems(ROOT / "bench"), _bench_problems(ROOT / "bench")


def test_the_bench_check_finds_a_sibling_import_and_a_path_edit(tmp_path):
    bench = tmp_path / "bench"
    bench.mkdir()
    (bench / "common.py").write_text("X = 1\n")
    (bench / "a.py").write_text('import sys\nsys.path.insert(0, ".")\nfrom common import X\n'
                                'if __name__ == "__main__":\n    pass\n')
    (bench / "b.py").write_text('from bench.a import X\nfrom bench.common import X\n')
    assert _bench_problems(bench) == ["a.py imports its sibling common by bare name",
                                              "a.py touches sys.path", "b.py imports the script a"]


def _private_uses(package: Path) -> list[str]:
    """Uses of another module's ``_private`` names inside ``package``: ``from X import _name`` and ``X._name``
    where X is another module of the package (imported under any alias, or spelled out as ``pkg.mod._name``)."""
    root = package.parent
    modules = {".".join(p.relative_to(root).with_suffix("").parts).removesuffix(".__init__"): p
               for p in sorted(package.rglob("*.py"))}
    found = []
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        aliases = {}  # local name -> module it stands for
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and not node.level and node.module in modules:
                for alias in node.names:
                    target = f"{node.module}.{alias.name}"
                    if target in modules:
                        aliases[alias.asname or alias.name] = target
                    elif alias.name.startswith("_") and not alias.name.startswith("__") and node.module != name:
                        found.append(f"{name} imports {node.module}.{alias.name}")
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name in modules:
                        aliases[alias.asname or alias.name.split(".")[0]] = alias.asname and alias.name
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
                owner = _dotted(node.value)
                if owner is None:
                    continue
                head, _, rest = owner.partition(".")
                module = aliases.get(head) or head
                module = f"{module}.{rest}" if rest else module
                if module in modules and module != name:
                    found.append(f"{name} uses {module}.{node.attr}")
    return sorted(set(found))


def _dotted(node) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        inner = _dotted(node.value)
        return None if inner is None else f"{inner}.{node.attr}"
    return None


@pytest.mark.parametrize("package", PACKAGES)
def test_no_module_uses_another_modules_private_names(package):
    assert not _private_uses(ROOT / package), _private_uses(ROOT / package)


def test_the_private_name_check_finds_imports_and_attributes(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    for path in (pkg / "__init__.py", pkg / "sub" / "__init__.py"):
        path.write_text("")
    (pkg / "sub" / "a.py").write_text("_STATE = {}\ndef _helper():\n    return _STATE\n")
    (pkg / "b.py").write_text("from pkg.sub.a import _helper\nfrom pkg.sub import a\nimport pkg.sub.a as m\n"
                              "import pkg.sub.a\nx = a._STATE, m._helper, pkg.sub.a._STATE, a.__name__\n")
    assert _private_uses(pkg) == ["pkg.b imports pkg.sub.a._helper", "pkg.b uses pkg.sub.a._STATE",
                                  "pkg.b uses pkg.sub.a._helper"]


def _scene_calls(root: Path) -> list[str]:
    """``file:line`` of every pyrender Scene built under ``root`` (``pyrender.Scene(...)`` or an imported
    ``Scene(...)``), relative to ``root``."""
    found = []
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        names = {alias.asname or alias.name for node in ast.walk(tree)
                 if isinstance(node, ast.ImportFrom) and node.module == "pyrender"
                 for alias in node.names if alias.name == "Scene"}
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and (
                    (isinstance(node.func, ast.Attribute) and node.func.attr == "Scene")
                    or (isinstance(node.func, ast.Name) and node.func.id in names)):
                found.append(f"{path.relative_to(root).as_posix()}:{node.lineno}")
    return found


def test_every_pyrender_scene_is_built_by_ordered_scene():
    # a plain pyrender Scene draws meshes and sums lights in memory-address order: the same input gave other pixels
    # (hoidata/render/renderer.py, "Same input, same pixels"); only ordered_scene builds one
    calls = [call for top in ("hoidata", "hoisdf", "bench") for call in
             (f"{top}/{c}" for c in _scene_calls(ROOT / top))]
    assert len(calls) == 1 and calls[0].startswith("hoidata/render/renderer.py:"), calls


def test_the_scene_check_finds_both_spellings(tmp_path):
    (tmp_path / "a.py").write_text("import pyrender\ns = pyrender.Scene(bg_color=(0, 0, 0))\n")
    (tmp_path / "b.py").write_text("from pyrender import Scene as S\n\n\ndef f():\n    return S()\n")
    (tmp_path / "c.py").write_text("from hoidata.render.renderer import ordered_scene\ns = ordered_scene()\n")
    assert _scene_calls(tmp_path) == ["a.py:2", "b.py:5"]
