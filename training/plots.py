"""Figures logged to MLflow: confusion matrix, error box plots (Zimmermann et al. 2018 §3.3 style), learning curves,
pose errors per segment, skeleton snapshots, and the flex figures (errors per joint, angle traces, robustness curves,
the ablation bars)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from service.core.segments import SEGMENTS  # noqa: E402


def _save(fig: plt.Figure, path: Path, dpi: int = 110) -> Path:
    """Write ``fig`` to ``path`` and free it."""
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def confusion_matrix_png(cm: np.ndarray, path: Path, title: str) -> Path:
    fig, ax = plt.subplots(figsize=(7, 6))
    frac = cm / np.maximum(cm.sum(axis=1, keepdims=True), 1)
    ax.imshow(frac, cmap="Blues", vmin=0, vmax=1)
    for i in range(cm.shape[0]):
        for j in range(cm.shape[1]):
            ax.text(
                j,
                i,
                f"{100 * frac[i, j]:.1f}",
                ha="center",
                va="center",
                color="white" if frac[i, j] > 0.5 else "black",
                fontsize=8,
            )
    ax.set_xticks(range(len(SEGMENTS)), SEGMENTS, rotation=45, ha="right")
    ax.set_yticks(range(len(SEGMENTS)), SEGMENTS)
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    ax.set_title(f"{title} (row %, n={int(cm.sum())})")
    fig.tight_layout()
    return _save(fig, path)


def error_boxplot_png(segment: np.ndarray, err_deg: np.ndarray, path: Path, title: str) -> Path:
    """Box plots of |error| about the segment x, y, z axes per segment; white circle = mean."""
    fig, axes = plt.subplots(1, 3, figsize=(15, 5), sharey=True)
    for ax_i, ax in enumerate(axes):
        data = [err_deg[segment == k, ax_i] for k in range(len(SEGMENTS))]
        ax.boxplot(
            data, showmeans=True, meanprops={"marker": "o", "markerfacecolor": "white"}, showfliers=False, whis=1.5
        )
        ax.set_xticks(range(1, len(SEGMENTS) + 1), SEGMENTS, rotation=45, ha="right")
        ax.set_title(f"axis {'xyz'[ax_i]} (ax{ax_i})")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("absolute error angle [deg]")
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def learning_curves_png(history: list[dict[str, float]], path: Path, title: str) -> Path:
    fig, ax = plt.subplots(figsize=(7, 4))
    epochs = np.arange(1, len(history) + 1)
    for key in ("train_loss", "val_loss"):
        ax.plot(epochs, [h[key] for h in history], label=key)
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss")
    ax.set_yscale("log")
    ax.legend()
    ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)


def held_out_bars_png(folds: dict[str, dict[str, float]], path: Path, title: str) -> Path:
    """Real-data leave-one-person-out: per held-out person, accuracy per window and one-to-one per moment, each
    with and without left/right (``training.i2s.pipeline.run_real_loso``)."""
    keys = [
        ("real_accuracy", "per window"),
        ("real_accuracy_ignoring_side", "per window, ignoring left/right"),
        ("real_window_joint_accuracy", "per moment"),
        ("real_window_joint_accuracy_ignoring_side", "per moment, ignoring left/right"),
    ]
    names = list(folds)
    fig, ax = plt.subplots(figsize=(2.4 + 1.1 * len(names), 5.5))
    width = 0.8 / len(keys)
    for k, (key, label) in enumerate(keys):
        x = np.arange(len(names)) + (k - (len(keys) - 1) / 2) * width
        ax.bar(x, [100 * folds[n][key] for n in names], width, label=label)
    ax.set_xticks(
        range(len(names)),
        [f"{n}\n(n={int(folds[n]['n_windows'])})" for n in names],
        rotation=30 if len(names) > 4 else 0,
        fontsize=8,
    )
    ax.set_ylim(0, 100)
    ax.set_ylabel("held-out accuracy (%)")
    ax.set_title(title)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=2)  # below: bars reach 100 %
    fig.tight_layout()
    return _save(fig, path)


def pose_learning_curve_png(history: list[dict[str, float]], path: Path, title: str) -> Path:
    """Training loss and the validation subjects' mean angle per epoch (how far from convergence a run stopped)."""
    fig, ax = plt.subplots(figsize=(7, 4))
    epochs = [h["epoch"] for h in history]
    ax.plot(epochs, [h["train_loss"] for h in history], label="train loss (rotation-matrix MSE)", color="C0")
    ax.set_xlabel("epoch")
    ax.set_ylabel("train loss")
    ax2 = ax.twinx()
    ax2.plot(epochs, [h["val_angle_deg"] for h in history], label="validation angle (deg)", color="C1")
    ax2.set_ylabel("validation mean angle (deg)")
    fig.legend(loc="upper right")
    ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)


def data_selection_png(trace: list[float], frames: dict[str, tuple[int, int]], path: Path, title: str) -> Path:
    """Zheng et al. 2021 §5: the score of eq. 4 after each deletion, and per activity the frames of the similar data
    (D_B) against those kept (D)."""
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    a.plot(range(len(trace)), trace, color="C0")
    a.set_xlabel("deletions")
    a.set_ylabel("f(D), eq. 4")
    names = sorted(frames, key=lambda k: -frames[k][0])[:25]
    x = np.arange(len(names))
    b.bar(x - 0.2, [frames[n][0] / 60.0 for n in names], 0.4, label="similar (D_B)", color="0.6")
    b.bar(x + 0.2, [frames[n][1] / 60.0 for n in names], 0.4, label="selected (D)", color="C0")
    b.set_xticks(x, names, rotation=60, ha="right", fontsize=7)
    b.set_ylabel("seconds")
    b.legend()
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def placement_png(
    relevance: np.ndarray, positions: tuple[str, ...], order: list[str], phi: list[float], path: Path, title: str
) -> Path:
    """Zheng et al. 2021 §6: the relevance between positions (eq. 15) in the greedy order, and Φ (eq. 18) as each
    position joins."""
    rank = list(order) + [p for p in positions if p not in order]
    idx = [positions.index(p) for p in rank]
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 5), gridspec_kw={"width_ratios": [1.3, 1]})
    im = a.imshow(relevance[np.ix_(idx, idx)], cmap="viridis")
    a.set_xticks(range(len(rank)), rank, rotation=70, ha="right", fontsize=7)
    a.set_yticks(range(len(rank)), rank, fontsize=7)
    a.set_title("relevance (mean MIC), greedy order first")
    fig.colorbar(im, ax=a, fraction=0.046)
    b.plot(range(1, len(phi) + 1), phi, "o-", color="C0")
    for k, (name, value) in enumerate(zip(order, phi, strict=True)):
        b.annotate(name, (k + 1, value), fontsize=7, rotation=30, xytext=(3, 3), textcoords="offset points")
    b.set_xlabel("sensors")
    b.set_ylabel("Φ = T − R (eq. 18)")
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def pose_segment_errors_png(per_segment: dict[str, float], sensors: list[str], path: Path, title: str) -> Path:
    """Mean global orientation error per segment; the sensors' own segments in grey."""
    names = list(per_segment)
    fig, ax = plt.subplots(figsize=(9, 4))
    colors = ["0.6" if n in sensors else "C0" for n in names]
    ax.bar(range(len(names)), [per_segment[n] for n in names], color=colors)
    ax.set_xticks(range(len(names)), names, rotation=60, ha="right", fontsize=8)
    ax.set_ylabel("mean angle error (deg)")
    ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)


def skeleton_snapshots_png(
    p_true: np.ndarray, p_pred: np.ndarray, parents: tuple[int, ...], frames: list[int], path: Path, title: str
) -> Path:
    """Stick figures of prediction (blue) against truth (grey), front (y–z) and side (x–z) views, some frames.

    ``p_*``: joint positions (T, S, 3) in the body's heading frame, pelvis at the origin.
    """
    fig, axes = plt.subplots(2, len(frames), figsize=(2.2 * len(frames), 5.5), squeeze=False)
    for col, t in enumerate(frames):
        for row, (a, b, view) in enumerate(((1, 2, "front"), (0, 2, "side"))):
            ax = axes[row, col]
            for p, color, width in ((p_true, "0.6", 3.0), (p_pred, "C0", 1.5)):
                for k, parent in enumerate(parents):
                    if parent >= 0:
                        ax.plot([p[t, parent, a], p[t, k, a]], [p[t, parent, b], p[t, k, b]], color=color, lw=width)
            ax.set_aspect("equal")
            ax.set_xlim(-0.9, 0.9)
            ax.set_ylim(-1.1, 0.9)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"frame {t} {view}", fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path, dpi=100)


def flex_learning_curve_png(history: list[dict[str, float]], path: Path, title: str) -> Path:
    """Training loss (standardised squared error, eq. 3 of Chen et al. 2024) and validation error per epoch, one
    pair of curves per member where several networks were trained (``member`` in the rows)."""
    fig, ax = plt.subplots(figsize=(7, 4))
    ax2 = ax.twinx()
    members = sorted({int(h.get("member", 0)) for h in history})
    for k in members:
        rows = [h for h in history if int(h.get("member", 0)) == k]
        suffix = f", member {k}" if len(members) > 1 else ""
        alpha = 1.0 - 0.6 * k / max(1, len(members) - 1)  # the first member darkest
        ax.plot([h["train_loss"] for h in rows], color="C0", alpha=alpha, label=f"train loss{suffix}")
        ax2.plot([h["val_mae_deg"] for h in rows], color="C1", alpha=alpha, label=f"validation error (deg){suffix}")
    ax.set_xlabel("epoch")
    ax.set_ylabel("train loss (standardised MSE)")
    ax2.set_ylabel("validation mean tracking error (deg)")
    fig.legend(loc="upper right")
    ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)


def bars_png(values: dict[str, float], path: Path, title: str, ylabel: str, highlight: list[str] | None = None) -> Path:
    """One bar per key (joints, activities or models); ``highlight`` keys in a second colour."""
    names = list(values)
    fig, ax = plt.subplots(figsize=(max(6, 0.55 * len(names) + 2), 4))
    colors = ["C1" if highlight and n in highlight else "C0" for n in names]
    ax.bar(range(len(names)), [values[n] for n in names], color=colors)
    ax.set_xticks(range(len(names)), names, rotation=50, ha="right", fontsize=8)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)


def curves_png(
    x: list[float], curves: dict[str, list[float]], path: Path, title: str, xlabel: str, ylabel: str
) -> Path:
    """One line per model over a swept condition (e.g. error against sensor ageing)."""
    fig, ax = plt.subplots(figsize=(7, 4))
    for k, (name, ys) in enumerate(curves.items()):
        ax.plot(x, ys, marker="o", color=f"C{k}", label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def traces_png(
    t_s: np.ndarray, truth: dict[str, np.ndarray], pred: dict[str, np.ndarray], path: Path, title: str
) -> Path:
    """Predicted against true angle over time, one panel per named angle."""
    fig, axes = plt.subplots(len(truth), 1, figsize=(9, 1.8 * len(truth) + 0.6), sharex=True, squeeze=False)
    for ax, name in zip(axes[:, 0], truth, strict=True):
        ax.plot(t_s, truth[name], color="0.3", label="truth")
        ax.plot(t_s, pred[name], color="C1", label="predicted")
        ax.set_ylabel(f"{name} (deg)", fontsize=8)
    axes[0, 0].legend(fontsize=8, loc="upper right")
    axes[0, 0].set_title(title)
    axes[-1, 0].set_xlabel("time (s)")
    fig.tight_layout()
    return _save(fig, path)


def reliability_png(
    p: np.ndarray,
    correct: np.ndarray,
    path: Path,
    title: str,
    bins: int = 10,
    what: tuple[str, str] = ("p_correct", "sensors"),
) -> Path:
    """Reliability diagram: per probability bin, the share right against the mean probability, with counts."""
    edges = np.linspace(0.0, 1.0, bins + 1)
    which = np.clip(np.digitize(p, edges[1:-1]), 0, bins - 1)
    fig, (ax, bx) = plt.subplots(2, 1, figsize=(5.5, 6.5), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    ax.plot([0, 1], [0, 1], color="grey", lw=1, ls="--", label="calibrated")
    xs = [p[which == b].mean() for b in range(bins) if (which == b).any()]
    ys = [correct[which == b].mean() for b in range(bins) if (which == b).any()]
    ax.plot(xs, ys, "o-", label="held-out people")
    ax.set_ylabel("share of assignments right")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper left")
    bx.bar((edges[:-1] + edges[1:]) / 2, [(which == b).sum() for b in range(bins)], width=0.09)
    bx.set_yscale("log")
    bx.set_xlabel(f"{what[0]} (calibrated on the other people)")
    bx.set_ylabel(what[1])
    fig.tight_layout()
    return _save(fig, path)


def velocity_learning_curve_png(history: list[dict[str, float]], path: Path) -> Path:
    """The velocity network's training loss and its validation displacement error per epoch."""
    fig, ax = plt.subplots(figsize=(7, 4))
    epochs = [h["epoch"] for h in history]
    ax.plot(epochs, [h["train_loss"] for h in history], label="train loss (accumulated displacement)", color="C0")
    ax.set_xlabel("epoch")
    ax.set_ylabel("train loss")
    ax2 = ax.twinx()
    val = [h["val_velocity_1s_cm"] for h in history]
    ax2.plot(epochs, val, label="validation, velocity alone (cm per 1 s)", color="C1")
    ax2.set_ylabel("validation displacement error (cm per 1 s)")
    fig.legend(loc="upper right")
    ax.set_title("learned pelvis velocity")
    fig.tight_layout()
    return _save(fig, path)


def translation_bars_png(errors: dict[str, dict[str, float]], share: float, path: Path) -> Path:
    """Per activity, the pelvis displacement error over 1 s: the rule, the rule with the learned velocity, the
    learned velocity alone and a pelvis kept in place."""
    activities = sorted(errors)
    series = [
        ("rule", "supporting-foot rule"),
        (f"share_{share:g}", f"rule + learned velocity ({share:g})"),
        ("velocity", "learned velocity alone (horizontal)"),
        ("still", "pelvis kept in place"),
    ]
    fig, ax = plt.subplots(figsize=(max(6.0, 1.2 * len(activities)), 4))
    width = 0.8 / len(series)
    for k, (key, label) in enumerate(series):
        ax.bar(
            np.arange(len(activities)) + k * width, [errors[a].get(key, np.nan) for a in activities], width, label=label
        )
    ax.set_xticks(np.arange(len(activities)) + 0.4 - width / 2, activities)
    ax.set_ylabel("pelvis displacement error (cm per 1 s)")
    ax.set_title("held-out subjects")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)
