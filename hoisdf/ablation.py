"""The paper's ablation tables, trained side by side on the same data: ``python -m hoisdf.toy --ablation NAME``.

Each table (:data:`TABLES`) lists its rows as the supplementary describes them: the training settings of the
variant, the inference settings (if they differ) and the paper's DexYCB numbers (mm). Rows with the same
training settings share one training run (the "field gradient" row trains exactly as "absolute distance" and
moves its query points only at inference). Every run starts from the same seed on the same stores with the same
number of steps; every row is evaluated on the same test store beside one mean-pose baseline. Outputs in
``OUT``: ``runs/<run>/`` (training runs), ``eval/<row>/`` (``hoisdf.evaluate`` outputs), ``table.md``,
``table.json`` and ``ablation.png`` (this run's errors next to the paper's).

The feature-augmentation rows run with ``cross_field = "none"``: the supplementary removes the cross-field
tokens for that table, since the cross fields use the augmentation too (its "w SDF augmentation" row equals
the "w/o cross feature enhancement" row of the cross-field table, 10.8 mm MJE).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

from hoidata.atomic import atomic_path, write_atomic
from hoidata.errors import DataError

METRICS = ("rr_mje", "pa_mje", "oce", "mce", "add_s")
LABELS = {"rr_mje": "MJE", "pa_mje": "PA-MJE", "oce": "OCE", "mce": "MCE", "add_s": "ADD-S"}


@dataclass(frozen=True)
class Row:
    label: str
    train: tuple[str, ...]  # model/train overrides of the training run
    infer: tuple[str, ...] = ()  # model overrides at inference (on top of the training run's config)
    paper: dict[str, float] = field(default_factory=dict)  # DexYCB test, mm (HOISDF paper, Tables 5-8)


def _paper(*values) -> dict[str, float]:
    return dict(zip(METRICS, values))


NO_CROSS = 'model.cross_field="none"'
TABLES: dict[str, tuple[Row, ...]] = {
    "sampling": (
        Row("Random", ('model.sampling="random"',), paper=_paper(25.8, 13.5, 48.4, 53.7, 29.6)),
        Row("Signed distance", ('model.sampling="signed"',), paper=_paper(13.3, 6.58, 19.7, 30.7, 15.9)),
        Row("Field gradient", ('model.sampling="absolute"',), ('model.sampling="gradient"',),
            paper=_paper(10.1, 5.29, 18.5, 27.7, 13.5)),
        Row("Absolute distance (ours)", ('model.sampling="absolute"',), paper=_paper(10.1, 5.31, 18.4, 27.4, 13.3)),
    ),
    "feature_augmentation": (
        Row("w/o SDF augmentation", ('model.feature_augmentation="none"', NO_CROSS),
            paper=_paper(11.5, 6.05, 23.6, 31.2, 15.7)),
        Row("w density concatenation", ('model.feature_augmentation="density_concat"', NO_CROSS),
            paper=_paper(11.0, 5.71, 22.7, 30.5, 15.3)),
        Row("w distance concatenation", ('model.feature_augmentation="distance_concat"', NO_CROSS),
            paper=_paper(11.5, 6.07, 23.3, 30.9, 15.6)),
        Row("w SDF augmentation", ('model.feature_augmentation="density"', NO_CROSS),
            paper=_paper(10.8, 5.68, 22.2, 30.0, 15.1)),
    ),
    "cross_field": (
        Row("w/o cross feature enhancement", (NO_CROSS,), paper=_paper(10.8, 5.68, 22.2, 30.0, 15.1)),
        Row("w cross image feature", ('model.cross_field="image"',), paper=_paper(11.1, 5.74, 20.2, 28.6, 14.2)),
        Row("w cross target feature", ('model.cross_field="target"',), paper=_paper(11.3, 5.81, 23.7, 31.8, 15.9)),
        Row("Cross feature enhancement (ours)", ('model.cross_field="sdf"',),
            paper=_paper(10.1, 5.31, 18.4, 27.4, 13.3)),
    ),
    "pose_regressor": (
        Row("w/o intermediate joint regression", ('model.pose_regressor="mano_only"',), paper=_paper(10.4, 5.49)),
        Row("w/o MANO regression", ('model.pose_regressor="voting"',), paper=_paper(10.5, 5.65)),
        Row("w MANO shape & inverse kinematics", ('model.pose_regressor="ik"',), paper=_paper(10.0, 5.35)),
        Row("MANO regression (ours)", ('model.pose_regressor="mano"',), paper=_paper(10.1, 5.31)),
    ),
}


def slug(text: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in text.lower()).strip("_")


def training_runs(rows) -> dict[tuple[str, ...], str]:
    """Distinct training settings -> run folder name: the label of the row that trains and evaluates with them
    (no inference overrides), else of the first row using them."""
    runs: dict[tuple[str, ...], str] = {}
    for row in sorted(rows, key=lambda r: bool(r.infer)):
        runs.setdefault(row.train, slug(row.label))
    return {train: runs[train] for train in dict.fromkeys(r.train for r in rows)}


def derive_checkpoint(run_dir: Path, overrides: tuple[str, ...], out: Path) -> Path:
    """A copy of ``run_dir``'s last checkpoint (model weights, progress) whose config has the inference
    ``overrides`` applied: the same network evaluated with another inference setting."""
    from hoisdf.config import overridden_config
    from hoisdf.training.checkpoint import (
        CHECKPOINTS,
        LAST,
        load_checkpoint,
        save_checkpoint,
    )

    payload = load_checkpoint(run_dir)
    config = overridden_config(payload["config"], list(overrides), run_dir / "config.json")
    return save_checkpoint(out / CHECKPOINTS / LAST, {"model": payload["model"], "config": config.as_dict(),
                                                       "progress": payload.get("progress", {})})


def train_variant(run_dir: Path, store: Path, mano: Path, config: str, steps: int, seed: int,
                  overrides: list[str]) -> float | None:
    """Train one variant to ``steps`` steps, resuming an interrupted run; None when it had already finished."""
    from hoisdf.train import main as train_main
    from hoisdf.training.checkpoint import CHECKPOINTS, LAST, load_checkpoint

    resume = (run_dir / CHECKPOINTS / LAST).is_file()
    if resume and load_checkpoint(run_dir)["progress"]["global_step"] >= steps:
        return None
    argv = ["--shards", str(store), "--mano", str(mano), "--config", config, "--out", str(run_dir), "--no-progress",
            *(["--resume"] if resume else []), f"train.max_steps={steps}", f"train.seed={seed}", *overrides]
    print(f"\n$ python -m hoisdf.train {' '.join(argv)}", flush=True)
    start = time.perf_counter()
    if train_main(argv):
        raise DataError(run_dir, None, "training this ablation variant failed (its error is above)")
    return round(time.perf_counter() - start, 1)


def run_table(name: str, train_store: Path, test_store: Path, mano: Path, out: Path, steps: int, seed: int,
              extra: list[str], vis: int = 0, config: str = "toy") -> dict:
    """Train every distinct variant of table ``name`` (``--config config``, ``extra`` overrides, ``steps`` steps),
    evaluate every row on ``test_store``, write the table files into ``out``; returns the table's content."""
    from hoisdf.evaluate import evaluate

    if name not in TABLES:
        raise ValueError(f"unknown ablation {name!r}; choose one of {sorted(TABLES)}")
    rows, out = TABLES[name], Path(out)
    runs, timing = training_runs(rows), {}
    for overrides, run_name in runs.items():
        seconds = train_variant(out / "runs" / run_name, train_store, mano, config, steps, seed, [*extra, *overrides])
        if seconds is not None:
            timing[run_name] = seconds
    results = []
    for row in rows:
        ckpt = out / "runs" / runs[row.train]
        if row.infer:
            ckpt = derive_checkpoint(ckpt, row.infer, out / "derived" / slug(row.label))
        result = evaluate(ckpt, [test_store], mano, out / "eval" / slug(row.label), vis=vis, plausibility=0,
                          baseline_store=train_store, progress=False)
        results.append({"label": row.label, "train": list(row.train), "infer": list(row.infer),
                        "run": runs[row.train], "ours": {k: result["overall"].get(k) for k in METRICS},
                        "paper": row.paper})
        baseline = {k: result["baseline"]["overall"].get(k) for k in METRICS}
    summary = {"table": name, "steps_per_variant": steps, "seed": seed, "train_store": str(train_store),
               "test_store": str(test_store), "extra_overrides": extra, "train_seconds": timing,
               "rows": results, "mean_pose_baseline": baseline}
    write_atomic(out / "table.json", json.dumps(summary, indent=2).encode())  # whole, or one line naming it
    write_atomic(out / "table.md", markdown_table(summary).encode())
    plot_table(summary, out / "ablation.png")
    return summary


def _fmt(value) -> str:
    return "-" if value is None else f"{value:.1f}"


def markdown_table(summary: dict) -> str:
    """The rows with this run's errors (mm) beside the paper's, and the baseline's."""
    head = " | ".join(f"{LABELS[m]} ours / paper" for m in METRICS)
    title = (f"{summary['table']} ablation: {summary['steps_per_variant']} steps per variant, seed {summary['seed']}; "
             "ours = toy test store, paper = DexYCB test (mm)")
    lines = [title, "", f"| variant | {head} |", "|---|" + "---|" * len(METRICS)]
    for r in summary["rows"]:
        cells = " | ".join(f"{_fmt(r['ours'][m])} / {_fmt(r['paper'].get(m))}" for m in METRICS)
        lines.append(f"| {r['label']} | {cells} |")
    base = " | ".join(f"{_fmt(summary['mean_pose_baseline'][m])} / -" for m in METRICS)
    lines.append(f"| mean-pose baseline | {base} |")
    return "\n".join(lines) + "\n"


def plot_table(summary: dict, png: Path) -> Path:
    """Grouped bars: this run's errors per metric and variant (left), the paper's (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = summary["rows"]
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8))
    width = 0.8 / len(rows)
    x = np.arange(len(METRICS))
    for ax, who, title in ((axes[0], "ours", f"this run (toy, {summary['steps_per_variant']} steps each)"),
                           (axes[1], "paper", "paper (DexYCB test)")):
        for i, r in enumerate(rows):
            values = [r[who].get(m) if r[who].get(m) is not None else np.nan for m in METRICS]
            ax.bar(x + (i - (len(rows) - 1) / 2) * width, values, width, label=r["label"])
        if who == "ours":
            base = [summary["mean_pose_baseline"].get(m) or np.nan for m in METRICS]
            ax.scatter(x, base, marker="_", s=900, color="k", label="mean-pose baseline", zorder=3)
        ax.set_xticks(x, [LABELS[m] for m in METRICS])
        ax.set_ylabel("mm (lower is better)")
        ax.set_title(title)
        ax.grid(True, axis="y", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{summary['table']} ablation")
    fig.tight_layout()
    png = Path(png)
    with atomic_path(png) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return png
