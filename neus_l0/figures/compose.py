"""Side-by-side PNGs of meshes: an overview with the feature boxes, and zoomed crops."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from neus_l0.atomic import atomic_path
from neus_l0.figures.render import ERROR_CMAP

#: Figure resolution (dots per inch).
DPI = 110


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
    _plt().close(fig)
    return path


def _colorbar(fig, axes, vmax: float, label: str) -> None:
    import matplotlib as mpl

    sm = mpl.cm.ScalarMappable(norm=mpl.colors.Normalize(0.0, vmax), cmap=ERROR_CMAP)
    cb = fig.colorbar(sm, ax=axes, fraction=0.04, pad=0.02, extend="max", shrink=0.9)
    cb.set_label(label, fontsize=8)
    cb.ax.tick_params(labelsize=7)


def overview_figure(path: str | Path, panels: list[tuple[str, np.ndarray]],
                    boxes: list[tuple[str, np.ndarray]], title: str,
                    vmax: float | None = None) -> Path:
    """Whole-object views side by side, each feature's crop box drawn and numbered.

    Args:
        path: output PNG.
        panels: (caption, (H, W, 3) RGB image) per column.
        boxes: (label, kind, (x0, y0, x1, y1) pixel box) per feature, in the panels'
            pixels (kind ``pit`` boxes are red, others blue).
        title: figure title.
        vmax: draw an error colour bar on [0, vmax] (error images).
    """
    plt = _plt()
    h, w = panels[0][1].shape[:2]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels) + 0.8, 4.2 * h / w + 1.0),
                             squeeze=False, layout="constrained")
    axes = axes[0]
    for ax, (caption, img) in zip(axes, panels, strict=True):
        ax.imshow(np.clip(img, 0, 1), interpolation="lanczos")
        for k, (_, kind, (x0, y0, x1, y1)) in enumerate(boxes):
            ax.add_patch(plt.Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, lw=0.8,
                                       ec="tab:red" if kind == "pit" else "tab:blue"))
            ax.text(x0 + 2, y0 + 2, str(k + 1), fontsize=7, va="top", ha="left",
                    color="tab:red" if kind == "pit" else "tab:blue")
        ax.set_title(caption, fontsize=10)
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
        ax.axis("off")
    legend = "  ".join(f"{k + 1}: {label}" for k, (label, _, _) in enumerate(boxes))
    fig.suptitle(_wrap(title, int(fig.get_figwidth() * 11)), fontsize=11)
    fig.supxlabel(_wrap(legend, int(fig.get_figwidth() * 16)), fontsize=7)
    if vmax is not None:
        _colorbar(fig, list(axes), vmax, "distance to the true surface (world units)")
    return _save(fig, path)


def _wrap(text: str, width: int) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width))


def crops_figure(path: str | Path, columns: list[str],
                 rows: list[tuple[str, list[np.ndarray], list[str]]], title: str,
                 vmax: float | None = None) -> Path:
    """A grid of zoomed crops: one row per feature, one column per mesh.

    Args:
        path: output PNG.
        columns: column headings.
        rows: (feature label, [(S, S, 3) RGB per column], [caption under each]) per row.
        title: figure title.
        vmax: draw an error colour bar on [0, vmax].
    """
    plt = _plt()
    n_r, n_c = len(rows), len(columns)
    cell = 2.1
    fig, axes = plt.subplots(n_r, n_c, figsize=(cell * n_c + (1.6 if vmax else 0.4),
                                                cell * n_r + 0.8), squeeze=False,
                             layout="constrained")
    for i, (label, imgs, captions) in enumerate(rows):
        for j, (img, cap) in enumerate(zip(imgs, captions, strict=True)):
            ax = axes[i, j]
            ax.imshow(np.clip(img, 0, 1), interpolation="lanczos")
            ax.set_xticks([])
            ax.set_yticks([])
            for s in ax.spines.values():
                s.set_color("0.7")
            if i == 0:
                ax.set_title(columns[j], fontsize=10)
            if cap:
                ax.set_xlabel(cap, fontsize=8)
            if j == 0:
                ax.set_ylabel(label, fontsize=9)
    fig.suptitle(_wrap(title, int(fig.get_figwidth() * 12)), fontsize=10)
    if vmax is not None:
        _colorbar(fig, axes.ravel().tolist(), vmax, "distance to the true surface (world units)")
    return _save(fig, path)
