"""NeuS's first up-sampling round along one camera ray into a pit, per sampler.

Along the ray: the coarse section weights of a trained model (NeuS's up-sampling weights at
the fixed sharpness 64), the piecewise-constant PDF that HVS (NeRF's ``sample_pdf``) draws
from, the L0-Sampler's piecewise-exponential interpolation ``a (b/a)^s`` of the same weights
after maxblur, where each sampler's fine samples land, and the true surface depth.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from neus_l0.errors import NeusL0Error
from neus_l0.figures.views import Camera

#: Points drawn per interval of the L0 interpolation.
CURVE_POINTS = 48


@dataclasses.dataclass
class PitRay:
    """A camera ray that hits the bottom of a pit.

    Attributes:
        feature: the pit (features.json entry); view: camera index; xy: (2,) pixel.
        origin, direction: (3,) world units, unit direction.
        t_surface: world-unit distance along the ray to the true surface (from gt_depth).
        below_centre: how far the hit lies below the pit's centre along its axis.
    """

    feature: dict
    view: int
    xy: np.ndarray
    origin: np.ndarray
    direction: np.ndarray
    t_surface: float
    below_centre: float


def find_pit_ray(scene_dir: str | Path, features: list[dict], cams: list[Camera],
                 name: str | None = None) -> PitRay:
    """The pixel (of any view) whose true surface hit lies deepest inside a pit.

    For each pit (or only the one called `name`) and view, the pixels inside the pit's
    projected box are lifted to 3D with ``gt_depth.npz``; the depth of a hit below the pit
    centre along the pit axis (minus a tenth of its distance from the axis, to prefer the
    middle of the bottom) scores it. The pit whose best pixel goes deepest relative to its
    radius wins.

    Raises:
        NeusL0Error: no pits, no gt_depth.npz, or no view sees into the pit.
    """
    from neus_l0.data.cameras import decompose_projection
    from neus_l0.figures.views import crop_box

    scene_dir = Path(scene_dir)
    pits = [f for f in features if f["kind"] == "pit" and f["axis"] is not None]
    if name is not None:
        pits = [f for f in pits if f["name"] == name]
    if not pits:
        raise NeusL0Error(f"{scene_dir / 'features.json'}: no pit"
                          + (f" named '{name}'" if name else ""))
    path = scene_dir / "gt_depth.npz"
    if not path.is_file():
        raise NeusL0Error(f"{path}: missing (needed to find a ray into a pit)")
    depths = np.load(path)
    best: PitRay | None = None
    best_key = None
    for v, cam in enumerate(cams):
        key = f"depth_{v}"
        if key not in depths.files:
            continue
        depth = depths[key].astype(np.float64)  # (H, W) camera z
        K, c2w = decompose_projection(cam.P)
        for f in pits:
            axis = f["axis"] / np.linalg.norm(f["axis"])
            if axis @ (c2w[:3, 3] - f["center"]) < 0:
                axis = -axis  # the axis points out of the pit, towards the camera side
            x0, y0, x1, y1 = crop_box(cam, f["center"], f["radius"], 1.0)
            xs = np.arange(max(0, int(np.ceil(x0))), min(cam.width, int(np.floor(x1)) + 1))
            ys = np.arange(max(0, int(np.ceil(y0))), min(cam.height, int(np.floor(y1)) + 1))
            if len(xs) == 0 or len(ys) == 0:
                continue
            gx, gy = np.meshgrid(xs, ys)
            z = depth[gy, gx].ravel()  # (P,)
            ok = np.isfinite(z)
            if not ok.any():
                continue
            px = np.stack([gx.ravel(), gy.ravel()], -1)[ok].astype(np.float64)
            d_cam = np.linalg.solve(K, np.c_[px, np.ones(len(px))].T).T  # (P, 3), z = 1
            X = c2w[:3, 3] + (d_cam * z[ok, None]) @ c2w[:3, :3].T  # (P, 3) world hits
            rel = X - f["center"]
            below = -(rel @ axis)  # (P,)
            lateral = np.linalg.norm(rel + below[:, None] * axis, axis=1)
            score = below - 0.1 * lateral
            i = int(np.argmax(score))
            k = (round(below[i] / f["radius"], 1), below[i])
            if best_key is None or k > best_key:
                d = c2w[:3, :3] @ d_cam[i]
                norm = np.linalg.norm(d)
                best_key = k
                best = PitRay(f, v, px[i], c2w[:3, 3].copy(), d / norm,
                              float(z[ok][i] * norm), float(below[i]))
    if best is None or best.below_centre <= 0:
        raise NeusL0Error(f"{path}: no view sees below the centre of "
                          + (f"pit '{name}'" if name else "any pit"))
    return best


@dataclasses.dataclass
class RayProfile:
    """One model's first up-sampling round along a ray (all positions: world units from the
    camera).

    Attributes:
        t: (N,) coarse samples; section_weights: (N-1,) NeuS's weights of [t_j, t_{j+1}].
        hvs_pdf: (N-1,) HVS density on each section (integrates to 1).
        l0_t: (M,) L0 nodes; l0_w: (M,) blurred node weights; l0_x, l0_pdf: dense curve of
            the piecewise-exponential density (integrates to 1).
        fine: {sampler: (n,) first-round fine samples}; fine_all: all rounds' fine samples
            of the run's own sampler; model_surface: first SDF zero crossing (or NaN).
        near, far: the sphere bounds.
    """

    t: np.ndarray
    section_weights: np.ndarray
    hvs_pdf: np.ndarray
    l0_t: np.ndarray
    l0_w: np.ndarray
    l0_x: np.ndarray
    l0_pdf: np.ndarray
    fine: dict
    fine_all: np.ndarray
    model_surface: float
    near: float
    far: float


def exp_interpolation(t: torch.Tensor, w: torch.Tensor,
                      per_interval: int = CURVE_POINTS) -> tuple[torch.Tensor, torch.Tensor]:
    """The L0 density ``a (b/a)^s`` on every interval of the nodes, normalised to mass 1.

    Args:
        t: (M,) sorted nodes; w: (M,) positive node weights (after maxblur).
        per_interval: points per interval.

    Returns:
        x, pdf: (M-1) * per_interval positions and densities.
    """
    from neus_l0.sampling.kernels import piece_mass

    a, b = w[:-1], w[1:]  # (M-1,)
    D = t[1:] - t[:-1]
    mass = (piece_mass(a, b, "exp") * D).sum()
    s = torch.linspace(0.0, 1.0, per_interval, dtype=t.dtype)  # (P,)
    x = t[:-1, None] + s[None] * D[:, None]  # (M-1, P)
    y = a[:, None] * (b / a)[:, None] ** s[None]  # (M-1, P)
    return x.reshape(-1), (y / mass).reshape(-1)


def section_pieces_curve(a: torch.Tensor, b: torch.Tensor, d: torch.Tensor, t_lo: torch.Tensor,
                         per_piece: int = CURVE_POINTS // 2
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """The exponential pieces of `neus_l0.sampling.kernels.l0_section_pieces`, normalised to mass 1.

    Args:
        a, b, d, t_lo: (1, K) piece start / end densities, lengths and starts.
        per_piece: points per piece.

    Returns:
        x, pdf: K * per_piece positions and densities.
    """
    from neus_l0.sampling.kernels import piece_mass

    a, b, d, t_lo = a[0], b[0], d[0], t_lo[0]  # (K,)
    mass = (piece_mass(a, b, "exp") * d).sum().clamp_min(1e-300)
    s = torch.linspace(0.0, 1.0, per_piece, dtype=a.dtype)  # (P,)
    ratio = torch.where(a > 0, b / torch.where(a > 0, a, 1.0), 0.0)
    y = a[:, None] * ratio[:, None] ** s[None]  # (K, P)
    return (t_lo[:, None] + s[None] * d[:, None]).reshape(-1), (y / mass).reshape(-1)


def ray_profile(model, cfg, origin: np.ndarray, direction: np.ndarray,
                scale_mat: np.ndarray, sampler: str) -> RayProfile:
    """Coarse weights, both samplers' densities and draws along one world-unit ray.

    Args:
        model: trained NeuS networks; cfg: their `Config`.
        origin, direction: (3,) world units (unit direction).
        scale_mat: (4, 4) normalised -> world (uniform scale).
        sampler: the sampler the run trained with (its all-round fine samples are drawn).
    """
    from neus_l0.bounds.sphere import near_far_from_sphere
    from neus_l0.data.cameras import to_normalised, world_scale
    from neus_l0.render.volume import coarse_z_vals, render_rays
    from neus_l0.sampling.kernels import l0_section_pieces, maxblur
    from neus_l0.sampling.upsample import build_sampler, upsample_section_weights

    r, sc = cfg.render, cfg.sampler
    s = world_scale(scale_mat)  # world units per normalised unit along the ray
    o = torch.as_tensor(to_normalised(origin, scale_mat), dtype=torch.float32)[None]  # (1, 3)
    d = torch.as_tensor(direction, dtype=torch.float32)[None]  # (1, 3): same in both frames
    with torch.no_grad():
        near, far = near_far_from_sphere(o, d)  # (1, 1)
        t = coarse_z_vals(near, far, r.n_samples, perturb=False)  # (1, N)
        pts = o[:, None] + d[:, None] * t[..., None]  # (1, N, 3)
        sdf = model.sdf.sdf(pts.reshape(-1, 3)).reshape(1, -1)
        sections = upsample_section_weights(t, sdf, pts.norm(dim=-1), sc.base_inv_s)
        w = sections.weights  # (1, N-1)
        per_round = max(1, r.n_importance // max(1, r.up_sample_steps))
        l0 = build_sampler(dataclasses.replace(sc, name="l0",
                                               l0=dataclasses.replace(sc.l0, kind="")))
        fine = {"hvs": build_sampler("hvs").draw(sections, per_round)[0] * s,
                "l0": l0.draw(sections, per_round)[0] * s}
        if l0.masses == "sections":  # the section weights' shares, the interpolant inside
            nodes = 0.5 * (t[:, 1:] + t[:, :-1])
            wb = (w[0] / (t[0, 1:] - t[0, :-1])).double()  # (M,) section densities
            x, pdf = section_pieces_curve(*l0_section_pieces(t.double(), w.double()))
        else:
            nodes, pw = l0.point_weights(sections)
            wb = maxblur(pw, pad=l0.pad)[0].double() if l0.blur else pw[0].double()  # (M,)
            x, pdf = exp_interpolation(nodes[0].double(), wb)
        D = (t[0, 1:] - t[0, :-1]).double()
        hvs = w[0].double() / (w[0].double().sum() * D)
        fine_all = (render_rays(model, o, d, r, build_sampler(sampler)).t_fine[0]
                    if r.n_importance else torch.zeros(0))
        # the model's surface: first sign change of its SDF on a dense grid
        t_dense = torch.linspace(float(near), float(far), 4000)[None]  # (1, 4000)
        dense = model.sdf.sdf((o[:, None] + d[:, None] * t_dense[..., None]).reshape(-1, 3))
        dense = dense.reshape(-1)  # (4000,)
        neg = torch.nonzero(dense <= 0)
        surf = float(t_dense[0, neg[0, 0]]) * s if len(neg) else float("nan")
    return RayProfile(
        t=t[0].numpy() * s, section_weights=w[0].numpy(), hvs_pdf=hvs.numpy() / s,
        l0_t=nodes[0].numpy() * s, l0_w=wb.numpy(), l0_x=x.numpy() * s, l0_pdf=pdf.numpy() / s,
        fine={k: v.numpy() for k, v in fine.items()}, fine_all=fine_all.numpy() * s,
        model_surface=surf, near=float(near) * s, far=float(far) * s)


#: Colours of the samplers in the plots.
COLORS = {"hvs": "tab:blue", "l0": "tab:orange"}


def plot_ray_weights(path: str | Path, ray: PitRay, profiles: list[tuple[str, str, RayProfile]],
                     title: str) -> Path:
    """One PNG: a row per trained run, the whole ray on the left and a zoom on the right.

    Args:
        path: output PNG.
        ray: the ray (for the true surface depth).
        profiles: (row heading, the run's sampler, profile) per run.
        title: figure title.
    """
    from neus_l0.figures.compose import _plt, _save

    plt = _plt()
    fig, axes = plt.subplots(len(profiles), 2, figsize=(13, 3.4 * len(profiles) + 1.3),
                             squeeze=False, gridspec_kw={"width_ratios": [1.2, 1]})
    below = 0.3  # fraction of each plot under 0 (sample ticks)
    for i, (heading, own, p) in enumerate(profiles):
        lo_z, hi_z = zoom_window(p, ray.t_surface)
        for j, ax in enumerate(axes[i]):
            lo, hi = (p.near, p.far) if j == 0 else (lo_z, hi_z)
            ax2 = ax.twinx()
            mids = 0.5 * (p.t[1:] + p.t[:-1])
            ax2.vlines(mids, 0, p.section_weights, color="0.55", lw=3, alpha=0.55,
                       label="coarse section weights (right axis)")
            wtop = max(1e-6, float(p.section_weights.max())) * 1.1
            ax2.set_ylim(-below / (1 - below) * wtop, wtop)  # zero aligned with the left axis
            ax2.set_yticks([t for t in ax2.get_yticks() if 0 <= t <= wtop])
            ax2.set_ylabel("coarse weight", fontsize=8, color="0.4")
            ax2.tick_params(labelsize=7, colors="0.4")
            ax.stairs(p.hvs_pdf, p.t, color=COLORS["hvs"], lw=1.5,
                      label="HVS: piecewise-constant PDF of the weights")
            ax.plot(p.l0_x, p.l0_pdf, color=COLORS["l0"], lw=1.5,
                    label="L0: the density its draw uses (exponential pieces)")
            ax.set_zorder(ax2.get_zorder() + 1)
            ax.patch.set_visible(False)
            trans = ax.get_xaxis_transform()
            rows = [("hvs", p.fine["hvs"], COLORS["hvs"], "hvs fine samples (round 1)"),
                    ("l0", p.fine["l0"], COLORS["l0"], "l0 fine samples (round 1)"),
                    (own, p.fine_all, "k", "the run's own sampler: fine samples of all rounds")]
            for k, (_, f, color, label) in enumerate(rows):
                if len(f):
                    ax.plot(f, np.full_like(f, below * (0.2 + 0.27 * k)), "|", ms=8, mew=1.2,
                            color=color, transform=trans, label=label)
            ax.axvline(ray.t_surface, color="k", ls="--", lw=1.2,
                       label="true surface (gt_depth)")
            if np.isfinite(p.model_surface):
                ax.axvline(p.model_surface, color="tab:green", ls=":", lw=1.6,
                           label="model surface (first SDF = 0)")
            ax.set_xlim(lo, hi)
            top = max(float(p.hvs_pdf.max()), float(p.l0_pdf.max()), 1e-12) * 1.1
            ax.set_ylim(-below / (1 - below) * top, top)
            ax.set_yticks([t for t in ax.get_yticks() if 0 <= t <= top])
            ax.axhline(0, color="0.75", lw=0.6)
            ax.set_ylabel("density (1 / world unit)", fontsize=8)
            ax.tick_params(labelsize=7)
            if i == len(profiles) - 1:
                ax.set_xlabel("distance along the ray from the camera (world units)", fontsize=9)
            which = "whole ray inside the unit sphere" if j == 0 else "zoom on the surface"
            ax.set_title(f"{heading}: {which}", fontsize=9)
            if i == 0 and j == 0:
                h1, l1 = ax.get_legend_handles_labels()
                h2, l2 = ax2.get_legend_handles_labels()
                handles, labels = h1 + h2, l1 + l2
    fig.suptitle(title, fontsize=11)
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.09 if len(profiles) > 1 else 0.15, 1, 1))
    return _save(fig, path)


def zoom_window(p: RayProfile, t_surface: float) -> tuple[float, float]:
    """A window holding the true surface, the model's surface and the central 96 % of the
    HVS density, with two coarse steps of margin (inside the ray's bounds)."""
    step = float(np.mean(np.diff(p.t)))
    cdf = np.cumsum(p.hvs_pdf * np.diff(p.t))
    pts = [t_surface]
    if cdf[-1] > 0:
        cdf = cdf / cdf[-1]
        pts += [p.t[1:][np.searchsorted(cdf, 0.02)], p.t[:-1][np.searchsorted(cdf, 0.98)]]
    if np.isfinite(p.model_surface):
        pts.append(p.model_surface)
    lo, hi = min(pts) - 2 * step, max(pts) + 2 * step
    return max(lo, p.near), min(hi, p.far)
