"""The static half of the guarded-door tests (tests/test_reading*.py): every call that opens or decodes a file's
bytes, found in the source by ``ast``, and every function that reads through the door (:mod:`hoidata.reading`,
:mod:`hoidata.reading_media`), so the corpus walk can check it fed each one."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOOR = ("hoidata.reading", "hoidata.reading_media")
# dotted call -> what it reads; a call of one of these outside the door bypasses it
RAW_READS = {
    "open": "a file", "io.open": "a file", "json.load": "JSON", "json.loads": "JSON", "numpy.load": ".npy/.npz",
    "numpy.loadtxt": "a text table", "numpy.genfromtxt": "a text table", "numpy.fromfile": "raw bytes",
    "zipfile.ZipFile": "a zip", "zipfile.is_zipfile": "a zip", "tarfile.open": "a tar", "cv2.imread": "an image",
    "cv2.imdecode": "an image", "PIL.Image.open": "an image", "trimesh.load": "a mesh", "trimesh.load_mesh": "a mesh",
    "yaml.safe_load": "YAML", "yaml.load": "YAML", "tomllib.load": "TOML", "tomllib.loads": "TOML",
    "torch.load": "a checkpoint", "pickle.load": "a pickle", "pickle.loads": "a pickle",
    ".read_text": "a text file", ".read_bytes": "a file",
}
WRITE_MODES = set("wax")


def _aliases(tree: ast.AST) -> dict[str, str]:
    """Local name -> dotted name, from the module's imports (``import numpy as np``: np -> numpy)."""
    out = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                out[alias.asname or alias.name.split(".")[0]] = alias.name if alias.asname else alias.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for alias in node.names:
                out[alias.asname or alias.name] = f"{node.module}.{alias.name}"
    return out


def _dotted(node, aliases: dict[str, str]) -> str | None:
    if isinstance(node, ast.Name):
        return aliases.get(node.id, node.id)
    if isinstance(node, ast.Attribute):
        inner = _dotted(node.value, aliases)
        return f"{inner}.{node.attr}" if inner else f".{node.attr}"
    return None


def _mode(call: ast.Call, position: int) -> str | None:
    args = [a for a in call.args[position:position + 1]] + [k.value for k in call.keywords if k.arg == "mode"]
    values = [a.value for a in args if isinstance(a, ast.Constant) and isinstance(a.value, str)]
    return values[0] if values else None


def raw_read(call: ast.Call, aliases: dict[str, str]) -> str | None:
    """The RAW_READS name a call is, or None (writes, and JSON that only copies a value, are not reads)."""
    name = _dotted(call.func, aliases)
    if name is None:
        return None
    method = "." + name.rsplit(".", 1)[-1] if isinstance(call.func, ast.Attribute) else None
    key = name if name in RAW_READS else method if method in (".read_text", ".read_bytes") else None
    if key is None:
        return None
    if key in ("open", "io.open", "tarfile.open", "zipfile.ZipFile"):
        mode = _mode(call, 1)
        if mode and WRITE_MODES & set(mode) and "+" not in mode:
            return None
    if key == "json.loads" and call.args and isinstance(call.args[0], ast.Call) and \
            _dotted(call.args[0].func, aliases) == "json.dumps":
        return None  # a value copied through JSON, not a file
    return key


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def package_modules():
    for package in ("hoidata", "hoisdf"):
        for path in sorted((ROOT / package).rglob("*.py")):
            yield _module_name(path), path


def _functions(tree: ast.AST):
    """(qualified name, node) of every function, nested ones as ``outer.<locals>.inner`` (``co_qualname``)."""
    def walk(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = f"{prefix}{child.name}"
                yield name, child
                yield from walk(child, f"{name}.<locals>.")
            elif isinstance(child, ast.ClassDef):
                yield from walk(child, f"{prefix}{child.name}.")
            else:
                yield from walk(child, prefix)
    yield from walk(tree, "")


def _own_calls(func: ast.AST):
    """Calls in a function's body (its lambdas and comprehensions included), not in the functions nested in it."""
    todo = list(ast.iter_child_nodes(func))
    while todo:
        node = todo.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            continue
        if isinstance(node, ast.Call):
            yield node
        todo.extend(ast.iter_child_nodes(node))


def raw_reads(modules=None) -> list[tuple[str, str, int, str]]:
    """(module, function, line, call) of every raw read outside the door."""
    found = []
    for module, path in modules or package_modules():
        if module in DOOR:
            continue
        tree = ast.parse(path.read_text(), str(path))
        aliases = _aliases(tree)
        seen = set()
        for qual, func in _functions(tree):
            for call in _own_calls(func):
                what = raw_read(call, aliases)
                if what:
                    found.append((module, qual, call.lineno, what))
                    seen.add(id(call))
        for node in ast.walk(tree):  # module level
            if isinstance(node, ast.Call) and id(node) not in seen and raw_read(node, aliases):
                if not any(node is c for _, f in _functions(tree) for c in ast.walk(f)):
                    found.append((module, "<module>", node.lineno, raw_read(node, aliases)))
    return found


def door_readers(modules=None) -> set[tuple[str, str]]:
    """(module, function qualname) of every function outside the door that calls one of its readers."""
    from hoidata import reading, reading_media

    entries = {f"{m.__name__}.{n}" for m in (reading, reading_media) for n in dir(m)
               if callable(getattr(m, n)) and not n.startswith("_") and getattr(getattr(m, n), "__module__", "")
               == m.__name__}
    entries = {e for e in entries if e.rsplit(".", 1)[1] in READER_ENTRIES}
    out = set()
    for module, path in modules or package_modules():
        if module in DOOR:
            continue
        tree = ast.parse(path.read_text(), str(path))
        aliases = _aliases(tree)
        for qual, func in _functions(tree):
            if any(_dotted(c.func, aliases) in entries for c in _own_calls(func)):
                out.add((module, qual))
    return out


# the door's entries that take a file (or a member's bytes) in: each caller of one is a reader to feed the corpus
READER_ENTRIES = {
    "read_bytes", "read_text", "read_lines", "read_json", "parse_json", "read_yaml", "read_toml", "read_table",
    "read_zip_member", "open_zip", "zip_read", "open_npz", "read_npz", "decode_npy", "list_tar", "read_span",
    "read_image", "decode_image", "decode_pil", "read_mesh", "decode_mesh", "read_torch",
}
