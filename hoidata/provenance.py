"""Where a result came from: the checkout's commit, recorded in every store's index and every training run's
``config.json``; and what a store records of its inputs, ``provenance["inputs"]`` of its index: the pipeline it was
built with, the preset that trains it and why, its dataset, MANO and models folders, and the sha256 of its MANO
files (copied from its ``build.json``). Training takes its MANO folder and preset from there; a recorded MANO folder
is used only while its ``MANO_RIGHT.pkl`` still has the recorded digest. A ground-floor module: both the build and
``hoisdf`` use it without reaching into either."""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path

from hoidata.errors import DataError
from hoidata.reading import file_digest


def git_commit() -> str:
    """The ``git rev-parse HEAD`` of the checkout this package runs from; "unknown" outside a git checkout (an
    installed wheel), without git, or when git does not answer within 5 s."""
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True, check=False,
                              text=True, timeout=5).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"

INPUTS = "inputs"  # the provenance key
MANO_VARIABLE = "MANO_DIR"  # the environment variable naming the MANO folder (docs/datasets.md, "Where the data is")
MANO_FILE = "MANO_RIGHT.pkl"  # the file whose digest identifies a MANO folder (training uses the right hand)


def recorded_inputs(index) -> dict:
    """A store index's record of its inputs; {} for a store built before stores recorded them."""
    value = index.provenance.get(INPUTS)
    return value if isinstance(value, dict) else {}


def mano_digest(folder) -> str | None:
    """The sha256 of ``folder/MANO_RIGHT.pkl``, None when there is no such file."""
    path = Path(folder) / MANO_FILE
    if not path.is_file():
        return None
    return file_digest(path, "MANO file")[1]


@dataclass(frozen=True)
class ManoChoice:
    folder: Path
    origin: str  # where the folder came from, for the line a command prints


def _recorded(stores) -> list[tuple[str, str, str]]:
    """(store, MANO folder, MANO_RIGHT.pkl digest) of every ``(store name, inputs)`` that records them."""
    out = []
    for name, inputs in stores:
        digests = inputs.get("mano_sha256")
        if inputs.get("mano") and isinstance(digests, dict) and isinstance(digests.get(MANO_FILE), str):
            out.append((str(name), str(inputs["mano"]), digests[MANO_FILE]))
    return out


def find_recorded_mano(stores, variable: str | None) -> ManoChoice | None:
    """The MANO folder the ``(store name, inputs)`` pairs were built with: the first recorded folder, then the
    folder ``variable`` names (:data:`MANO_VARIABLE`'s value), whose ``MANO_RIGHT.pkl`` has the recorded digest.
    None when no store records one. A DataError naming the store, ``--mano`` and the variable when none matches
    (the folder moved or its file changed), or when two stores were built with different MANO files."""
    recorded = _recorded(stores)
    if not recorded:
        return None
    name, folder, digest = recorded[0]
    other = next((r for r in recorded if r[2] != digest), None)
    if other is not None:
        raise DataError(other[0], "inputs.mano", f"built with another MANO_RIGHT.pkl than {name} ({other[1]} vs "
                                                 f"{folder}): train them apart, or pass --mano to use one for both")
    candidates = [(f, f"the build record of {n}") for n, f, _ in recorded]
    candidates += [(variable, f"{MANO_VARIABLE}, with the MANO_RIGHT.pkl {name} records")] if variable else []
    seen = set()
    for path, origin in candidates:
        if path not in seen and mano_digest(path) == digest:
            return ManoChoice(Path(path), origin)
        seen.add(path)
    state = "which is missing now" if mano_digest(folder) is None else "whose MANO_RIGHT.pkl has changed since"
    also = f"; {MANO_VARIABLE}={variable} holds another MANO_RIGHT.pkl" if variable else ""
    raise DataError(name, "inputs.mano", f"built with the MANO folder {folder}, {state}{also}: pass --mano DIR or "
                                         f"set {MANO_VARIABLE} to a folder with that MANO_RIGHT.pkl "
                                         f"(sha256 {digest[:16]}...)")
