"""`rasterize()`: one entry point with gsplat's calling convention, on CUDA (gsplat) or the CPU.

Splatfacto and the registration call this instead of `gsplat.rasterization`; with CUDA tensors and an
importable gsplat it *is* `gsplat.rasterization` (non-packed, so `info` has the [C, N] layout that
`gsplat.strategy.DefaultStrategy` expects). Elsewhere the CPU backends project with
`projection.project_gaussians` and composite with numba's tile compositor
(`numba_compositor.composite_camera_tiled`, backend "numba", the CPU default) or the pure-torch one
(`cpu_rasterizer.composite_camera`, backend "torch"; same image, slower), and return an `info` dict
with the same keys DefaultStrategy reads (`means2d` with retained grad, `radii`, `width`, `height`,
`n_cameras`, `gaussian_ids` None, ...).

Frames: `viewmats` are world-to-camera in the OpenCV convention (x right, y down, z forward), `Ks` pinhole
intrinsics in pixels, pixel (i, j) has its centre at (j + 0.5, i + 0.5) -- all as in gsplat.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Literal, Optional

import torch
from torch import Tensor

from sg_nerfstudio.render.cpu_rasterizer import composite_camera, front_to_back
from sg_nerfstudio.render.projection import (
    ProjectedGaussians,
    covariances_from_quats_scales,
    cull_gaussians,
    project_gaussians_packed,
)
from sg_nerfstudio.render.spherical_harmonics import evaluate_sh

Backend = Literal["auto", "gsplat", "numba", "torch"]
RenderMode = Literal["RGB", "D", "ED", "RGB+D", "RGB+ED"]
RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")


FROZEN_KERNELS = True
"""Project and colour a frozen model (Gaussians that need no gradient: registration) with the compiled kernels
of `frozen_projection` (gradients for the cameras only) instead of autograd; False restores the autograd path
(same outputs and gradients, slower; `bench.scaling` compares the two)."""


def frozen_kernels(*tensors: Tensor) -> bool:
    """Whether the compiled frozen-model kernels apply: none of `tensors` (CPU) needs a gradient and numba imports."""
    frozen = not any(tensor.requires_grad or tensor.device.type != "cpu" for tensor in tensors)
    return FROZEN_KERNELS and frozen and numba_available()


def gsplat_available() -> bool:
    """True when gsplat imports and CUDA is usable (its rasterizer has no CPU kernels)."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def numba_available() -> bool:
    """True when the numba tile compositor imports (numba is a dependency, but may be missing or broken)."""
    try:
        from sg_nerfstudio.render import numba_compositor  # noqa: F401
    except ImportError:
        return False
    return True


def resolve_backend(backend: Backend, device: torch.device) -> Literal["gsplat", "numba", "torch"]:
    """Pick the backend: 'auto' means gsplat for CUDA tensors when gsplat imports, else numba's CPU
    compositor when numba imports, else pure torch."""
    if backend == "torch":
        return "torch"
    if backend == "numba":
        if not numba_available():
            raise RuntimeError("backend='numba' needs the numba package (pip install numba); use backend='torch'.")
        return "numba"
    if backend == "gsplat":
        if device.type != "cuda" or not gsplat_available():
            raise RuntimeError(
                "backend='gsplat' needs CUDA tensors and an importable gsplat with CUDA; "
                f"got tensors on {device} (CUDA available: {torch.cuda.is_available()}). Use backend='auto'."
            )
        return "gsplat"
    if backend != "auto":
        raise ValueError(f"backend must be 'auto', 'gsplat', 'numba' or 'torch', got {backend!r}.")
    if device.type == "cuda" and gsplat_available():
        return "gsplat"
    return "numba" if numba_available() else "torch"


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    sh_degree: Optional[int] = None,
    backgrounds: Optional[Tensor] = None,
    render_mode: RenderMode = "RGB",
    rasterize_mode: Literal["classic", "antialiased"] = "classic",
    absgrad: bool = False,
    backend: Backend = "auto",
    covars: Optional[Tensor] = None,
) -> tuple[Tensor, Tensor, dict]:
    """Render N Gaussians into C cameras.

    Args:
        means: [N, 3] world-frame centres.
        quats: [N, 4] rotations (w, x, y, z), not necessarily normalised.
        scales: [N, 3] standard deviations (post-activation).
        opacities: [N] in [0, 1] (post-activation).
        colors: [N, D] any D (e.g. 3 RGB + 128 features) when `sh_degree` is None, else SH coefficients
            [N, K, 3] evaluated up to `sh_degree` (then +0.5 and clamped at 0, as gsplat does).
        viewmats: [C, 4, 4] world-to-camera, OpenCV.
        Ks: [C, 3, 3] pinhole intrinsics.
        width, height: image size in pixels.
        near_plane, far_plane: depth range in world units.
        eps2d: 2D blur added to projected covariances (pixels^2).
        backgrounds: [C, D] colour behind the Gaussians, or None for black.
        render_mode: "RGB" (colours), "D" (accumulated depth), "ED" (expected depth = D / alpha),
            "RGB+D", "RGB+ED" (depth appended as the last channel).
        rasterize_mode: "classic" or "antialiased" (opacity compensation of the 2D blur).
        absgrad: gsplat only (CUDA backward); the CPU backend has no absgrad and rejects it.
        backend: "auto", "gsplat", "numba" or "torch" (see `resolve_backend`).
        covars: [N, 3, 3] world-frame covariances; when given, `quats` and `scales` are ignored (may be
            None), as in gsplat. A frozen model passes them precomputed.

    Returns:
        render [C, H, W, D'], alphas [C, H, W, 1], info dict.
    """
    if covars is not None:
        quats = scales = None
    _check_inputs(means, quats, scales, covars, opacities, colors, viewmats, Ks, width, height, sh_degree, render_mode)
    chosen = resolve_backend(backend, means.device)
    if chosen == "gsplat":
        from gsplat.rendering import rasterization as gsplat_rasterization

        return gsplat_rasterization(
            means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
            viewmats=viewmats, Ks=Ks, width=width, height=height, near_plane=near_plane,
            far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree, packed=False,
            backgrounds=backgrounds, render_mode=render_mode, absgrad=absgrad,
            rasterize_mode=rasterize_mode, covars=covars,
        )
    if absgrad:
        raise ValueError("absgrad=True needs gsplat's CUDA backward; the CPU backend provides means2d.grad only.")
    if covars is None:
        covars = covariances_from_quats_scales(quats, scales)
    return _rasterize_cpu(
        means, covars, opacities, colors, viewmats, Ks, width, height, near_plane, far_plane,
        eps2d, sh_degree, backgrounds, render_mode, rasterize_mode, chosen,
    )


def _rasterize_cpu(
    means, covars, opacities, colors, viewmats, Ks, width, height, near_plane, far_plane,
    eps2d, sh_degree, backgrounds, render_mode, rasterize_mode, backend,
) -> tuple[Tensor, Tensor, dict]:
    """CPU backends. Culling runs without gradients on all N Gaussians; the visible (Gaussian, camera)
    pairs of all C cameras are then projected with gradients in one packed batch, so backward work scales
    with what the cameras see and the number of tensor operations does not grow with C."""
    if backend == "numba":
        from sg_nerfstudio.render.numba_compositor import composite_camera_tiled as composite
    else:
        composite = composite_camera
    n_cameras = viewmats.shape[0]
    antialiased = rasterize_mode == "antialiased"
    projection_args = dict(width=width, height=height, eps2d=eps2d, near_plane=near_plane, far_plane=far_plane)
    depths, visible = _project_visible(means, covars, viewmats, Ks, antialiased, projection_args)
    proj, entry_ids, entry_cameras = visible.projection, visible.gaussian_ids, visible.camera_ids
    counts = torch.bincount(entry_cameras, minlength=n_cameras).tolist()
    visible_ids = entry_ids.split(counts)
    radii = torch.zeros(n_cameras, means.shape[0], dtype=torch.int32).index_put_((entry_cameras, entry_ids), proj.radii)
    entry_opacities = opacities.index_select(0, entry_ids)
    if proj.compensations is not None:
        entry_opacities = entry_opacities * proj.compensations
    entry_colors = _entry_colors(colors, sh_degree, means, viewmats, entry_ids, entry_cameras)
    if render_mode in ("RGB+D", "RGB+ED"):
        entry_colors = torch.cat([entry_colors, proj.depths[:, None]], dim=-1)
    elif render_mode in ("D", "ED"):
        entry_colors = proj.depths[:, None]

    hidden_means2d = means.new_zeros(means.shape[0], 2)
    if means.requires_grad:
        # Training: DefaultStrategy reads the gradient of the loss w.r.t. info["means2d"] [C, N, 2] itself,
        # so rendering gathers the visible means back out of that very tensor.
        means2d = torch.stack([hidden_means2d.index_copy(0, ids, m) for ids, m in zip(visible_ids, proj.means2d.split(counts))])
        entry_means2d = [means2d[cam].index_select(0, ids) for cam, ids in enumerate(visible_ids)]
    else:  # frozen Gaussians (registration): no densification, no round trip
        entry_means2d = proj.means2d.split(counts)
        means2d = torch.stack([hidden_means2d.index_copy(0, ids, m.detach()) for ids, m in zip(visible_ids, entry_means2d)])
    opacities_all = opacities.detach().expand(n_cameras, -1).clone()
    opacities_all[entry_cameras, entry_ids] = entry_opacities.detach()
    renders, alphas = [], []
    per_camera = zip(
        entry_means2d, proj.conics.split(counts), proj.cov2d.split(counts), entry_opacities.split(counts), entry_colors.split(counts)
    )
    for cam_means2d, cam_conics, cam_cov2d, cam_opacities, cam_colors in per_camera:
        render, alpha = composite(cam_means2d, cam_conics, cam_cov2d, cam_opacities, cam_colors, width, height)
        renders.append(render)
        alphas.append(alpha)
    render = torch.stack(renders)
    alpha = torch.stack(alphas)

    if render_mode in ("ED", "RGB+ED"):
        render = torch.cat([render[..., :-1], render[..., -1:] / alpha.clamp(min=1e-10)], dim=-1)
    if backgrounds is not None:
        if render_mode in ("RGB+D", "RGB+ED"):
            backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(n_cameras, 1)], dim=-1)
        elif render_mode in ("D", "ED"):
            backgrounds = backgrounds.new_zeros(n_cameras, 1)
        render = render + (1.0 - alpha) * backgrounds[:, None, None, :]

    info = {
        "camera_ids": None,
        "gaussian_ids": None,
        "radii": radii,
        "means2d": means2d,
        "depths": depths,
        "opacities": opacities_all,
        "width": width,
        "height": height,
        "n_cameras": n_cameras,
        "backend": backend,
    }
    return render, alpha, info


@dataclass
class VisibleEntries:
    """Packed (Gaussian, camera) pairs with radii > 0, grouped by camera, front to back within a camera.

    Attributes:
        projection: `ProjectedGaussians` with leading shape [S] (differentiable).
        gaussian_ids: [S] int64 index into the N Gaussians.
        camera_ids: [S] int64 index into the C cameras, non-decreasing.
    """

    projection: ProjectedGaussians
    gaussian_ids: Tensor
    camera_ids: Tensor


def _project_visible(means, covars, viewmats, Ks, antialiased: bool, projection_args: dict) -> tuple[Tensor, VisibleEntries]:
    """Depths [C, N] of all means, and the exact projection of what each camera sees.

    A cheap conservative cull (means only) picks candidates; they are projected exactly in one packed batch
    (for Gaussians that need no gradient, a frozen model, in classic mode: the compiled
    `frozen_projection.project_frozen_packed`, gradients for the viewmats only), and those the exact test
    rejects (radii 0) are dropped, so the result equals culling with `project_gaussians` on all C x N pairs at
    a fraction of the cost."""
    depths, candidates = cull_gaussians(means, covars, viewmats, Ks, **projection_args)
    candidate_ids = [front_to_back(candidates[cam], depths[cam]) for cam in range(viewmats.shape[0])]
    gaussian_ids = torch.cat(candidate_ids) if candidate_ids else torch.zeros(0, dtype=torch.long)
    counts = torch.tensor([len(ids) for ids in candidate_ids], dtype=torch.long)
    camera_ids = torch.repeat_interleave(torch.arange(len(candidate_ids)), counts)
    entry_means, entry_covars = means.index_select(0, gaussian_ids), covars.index_select(0, gaussian_ids)
    if not antialiased and frozen_kernels(means, covars):
        # a frozen model (registration): compiled projection, gradients for the cameras only
        from sg_nerfstudio.render.frozen_projection import project_frozen_packed

        proj = project_frozen_packed(entry_means, entry_covars, viewmats, Ks, camera_ids, **projection_args)
    else:
        proj = project_gaussians_packed(entry_means, entry_covars, viewmats, Ks, camera_ids, calc_compensations=antialiased, **projection_args)
    kept = torch.nonzero(proj.radii > 0).squeeze(1)  # keeps the order
    kept_fields = {field.name: getattr(proj, field.name) for field in fields(proj)}
    kept_fields = {name: None if value is None else value.index_select(0, kept) for name, value in kept_fields.items()}
    return depths, VisibleEntries(ProjectedGaussians(**kept_fields), gaussian_ids[kept], camera_ids[kept])


def _entry_colors(
    colors: Tensor, sh_degree: Optional[int], means: Tensor, viewmats: Tensor, entry_ids: Tensor, entry_cameras: Tensor
) -> Tensor:
    """Colours [S, D] of packed (Gaussian `entry_ids`, camera `entry_cameras`) entries, SH evaluated
    towards each entry's camera centre (compiled for a frozen model: `frozen_projection.frozen_sh_colors`)."""
    if sh_degree is None:
        return colors.index_select(0, entry_ids)
    rotations, translations = viewmats[:, :3, :3], viewmats[:, :3, 3]
    camera_centres = -(rotations.transpose(1, 2) @ translations[:, :, None])[:, :, 0]  # [C, 3]
    if frozen_kernels(means, colors):
        # a frozen model (registration): compiled, gradients for the camera centres only
        from sg_nerfstudio.render.frozen_projection import frozen_sh_colors

        return frozen_sh_colors(means, colors, camera_centres, entry_ids, entry_cameras, sh_degree)
    dirs = means.index_select(0, entry_ids) - camera_centres.index_select(0, entry_cameras)
    return torch.clamp_min(evaluate_sh(sh_degree, dirs, colors.index_select(0, entry_ids)) + 0.5, 0.0)


def _check_inputs(means, quats, scales, covars, opacities, colors, viewmats, Ks, width, height, sh_degree, render_mode) -> None:
    n = means.shape[0]
    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}.")
    shaped = [("opacities", opacities, (n,))]
    shaped += [("covars", covars, (n, 3, 3))] if covars is not None else [("quats", quats, (n, 4)), ("scales", scales, (n, 3))]
    for name, tensor, shape in shaped:
        if tensor is None or tuple(tensor.shape) != shape:
            found = None if tensor is None else tuple(tensor.shape)
            raise ValueError(f"{name} must be {list(shape)} to match means, got {found}.")
    expected_dims = 2 if sh_degree is None else 3
    if colors.dim() != expected_dims or colors.shape[0] != n:
        layout = "[N, D]" if sh_degree is None else "[N, K, 3] SH coefficients"
        raise ValueError(f"colors must be {layout} with N={n}, got {tuple(colors.shape)}.")
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4):
        raise ValueError(f"viewmats must be [C, 4, 4], got {tuple(viewmats.shape)}.")
    if tuple(Ks.shape) != (viewmats.shape[0], 3, 3):
        raise ValueError(f"Ks must be [C, 3, 3] with C={viewmats.shape[0]}, got {tuple(Ks.shape)}.")
    if width <= 0 or height <= 0:
        raise ValueError(f"width and height must be positive, got {width}x{height}.")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}.")
