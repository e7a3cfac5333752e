"""Figures people look at (matplotlib, PNG, written atomically)."""

from __future__ import annotations

import numpy as np

from .io import write_bytes_atomic


def new_figure(nrows: int = 1, ncols: int = 1, figsize=(6.4, 4.8)):
    """A matplotlib `Figure` and its axes, with a constrained layout.

    Built with matplotlib's object API, not pyplot: the library never touches pyplot's global state or
    backend (a user's notebook keeps its own), and drawing needs no GUI.
    """
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout="constrained")
    return fig, fig.subplots(nrows, ncols)


PNG_COMPRESSION = 3  # zlib level: a figure of images encodes in half the time of PIL's 6, about 9 % larger


def figure_png(fig, dpi: int = 120) -> bytes:
    """A matplotlib figure drawn as PNG, in memory."""
    import io

    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=dpi, format="png", pil_kwargs={"compress_level": PNG_COMPRESSION})
    return buffer.getvalue()


def save_figure(fig, path, dpi: int = 120) -> None:
    """Save a matplotlib figure as PNG to `path` atomically."""
    write_bytes_atomic(path, figure_png(fig, dpi))


def plot_damage_versus_stage(path, stages: list[str], figures: dict[str, tuple[list, list]], title: str) -> None:
    """Damage figures versus stage, each with its 95 % interval as an error bar where it is known.

    **Arguments:** `stages` the stages' names (x axis, in order); `figures` name -> `(values, intervals)`, one value
    (dimensionless, NaN or None where not computed) and one `(low, high)` interval or None per stage; E3D is drawn
    dashed with squares, the others solid with dots. Written to `path` (PNG) atomically.
    """
    fig, ax = new_figure(figsize=(6, 3.8))
    stage_x = np.arange(len(stages))
    for k, (name, (values, intervals)) in enumerate(figures.items()):
        x = stage_x + 0.04 * (k - (len(figures) - 1) / 2)  # each figure a little aside: equal values' bars apart
        y = np.array([np.nan if v is None else float(v) for v in values])
        low, high = (np.array([np.nan if b is None or b[end] is None else float(b[end]) for b in intervals])
                     for end in (0, 1))
        bars = np.isfinite(y) & np.isfinite(low) & np.isfinite(high)
        line, = ax.plot(x, y, "s--" if name == "E3D" else "o-", label=name)
        if bars.any():
            ax.errorbar(x[bars], y[bars], yerr=np.vstack([y[bars] - low[bars], high[bars] - y[bars]]), fmt="none",
                        ecolor=line.get_color(), capsize=4)
    ax.set_xticks(stage_x)
    ax.set_xticklabels(stages)
    ax.set_xlabel("stage")
    ax.set_ylabel("damage parameter (bars: 95 % interval)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    save_figure(fig, path)


def plot_calibration_errors(stereo, path, names: list[str] | None = None) -> None:
    """Bar chart of per-view reprojection RMS (left, right, stereo pairs), dropped views marked."""
    n = max([*stereo.left.views, *stereo.left.dropped, *stereo.right.views, *stereo.right.dropped,
             *stereo.pairs, *stereo.missing, 0]) + 1
    x = np.arange(n)
    fig, ax = new_figure(figsize=(max(6.0, 0.45 * n + 2), 3.8))
    for offset, cal, label, colour in ((-0.27, stereo.left, "left", "tab:blue"), (0.0, stereo.right, "right", "tab:orange")):
        values = np.full(n, np.nan)
        values[cal.views] = cal.view_rms_px
        ax.bar(x + offset, values, width=0.27, label=f"{label} ({cal.rms_px:.3f} px)", color=colour)
        for d in cal.dropped:
            ax.annotate("dropped", (d + offset, 0), rotation=90, fontsize=7, ha="center", va="bottom", color=colour)
    values = np.full(n, np.nan)
    values[stereo.pairs] = stereo.pair_rms_px
    ax.bar(x + 0.27, values, width=0.27, label=f"stereo ({stereo.rms_px:.3f} px)", color="tab:green")
    for m in stereo.missing:
        ax.annotate("no board", (m, 0), rotation=90, fontsize=7, ha="center", va="bottom", color="tab:red")
    ax.set_xticks(x)
    ax.set_xticklabels(names if names is not None else [str(i) for i in x], rotation=60, fontsize=7, ha="right")
    ax.set_ylabel("reprojection RMS (px)")
    ax.set_title("Calibration: reprojection error per view")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    save_figure(fig, path)
