"""Cull the frozen reference once to what a meta-image's photos can see, and again only when the pose moves far.

The model is frozen and a registration moves its cameras little between steps, so rendering all N Gaussians
every step is wasted work: most lie outside every photo's view. `VisibleSubset` keeps the Gaussians that
widened frusta of the photos see at one pose (the field of view enlarged by `WIDEN` about the principal
point, everything in front of the camera rather than of the near plane) and hands that smaller model to the renderer
until the pose has rotated by more than `MAX_ROTATION_DEG` or a camera centre has moved by more than
`MAX_SHIFT` of that photo's median Gaussian depth; then it culls again around the new pose.

Why the result is the same image: a Gaussian that reaches a photo at any pose within those bounds reaches the
widened frustum at the cull pose. Widening by 1.6 adds at least 7° of half field of view for fields of view
up to 140° (10-13° for ordinary 40-90° photos), more than the 4° rotation bound plus the direction change that
a 3% shift of the camera gives (under 2°). `tests/test_register.py` checks renders with and without culling.

With `level_of_detail` (render pixels, > 0) the culled model is also coarsened for the photos' render size at
the cull pose (`level_of_detail.coarsen`: Gaussians far below a pixel merged per voxel), so that the cost of a
step follows the pixels the photos render rather than the size of the reference. With a `render_budget`, a
coarsened model that would still hold more Gaussians than the budget is planned again with voxels twice as large
(up to `MAX_VOXEL_DOUBLINGS` times): a reference of millions of Gaussians, whose trained Gaussians are each
about one render pixel and so rarely share a one-pixel voxel, is then rendered at a bounded cost per step,
while a model within the budget renders exactly as at `level_of_detail`.

`held_at` pins the model culled at one pose for every render until released: the verdict's probes around the result
(registration/optimize.py, `held_for_probes`) all render the result's model, within the cull's bounds.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import torch
from torch import Tensor

from sg_nerfstudio.geometry.frames import camera_to_world, viewmat
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.registration.level_of_detail import footprint_cells, merge, plan_merge
from sg_nerfstudio.registration.reference import ReferenceModel
from sg_nerfstudio.render.projection import cull_gaussians

WIDEN = 1.6
"""Factor on tan(field of view) of the culling frusta."""
MAX_ROTATION_DEG = 4.0
MAX_SHIFT = 0.03
"""Re-cull once the pose has rotated by more than MAX_ROTATION_DEG, or a camera centre has moved by more than
MAX_SHIFT times its photo's median Gaussian depth, since the last cull."""
MAX_VOXEL_DOUBLINGS = 2
"""The render budget may at most quadruple the voxel of `level_of_detail`: fast-cpu renders at 4x its teacher's grid,
so 4 render pixels are one descriptor cell, the finest detail its objective compares."""
CULL_NEAR = 1e-4
"""Culling keeps everything in front of a camera: a camera moving back brings Gaussians behind its near plane
in front of it."""


@dataclass
class CullingCamera:
    """One photo's camera as culling needs it: pose in the meta frame, pinhole K and size of its render."""

    cam_from_meta: Tensor  # [3, 4] float64
    K: Tensor  # [3, 3]
    width: int
    height: int


class VisibleSubset:
    """The reference restricted to what the photos see around the current pose (see the module docstring)."""

    def __init__(self, reference: ReferenceModel, cameras: list[CullingCamera], level_of_detail: float = 0.0, render_budget: int = 0):
        self.reference, self.cameras, self.level_of_detail, self.render_budget = reference, cameras, level_of_detail, render_budget
        self.voxel_pixels = 0.0  # the voxel (render pixels) of the last coarsening; 0: none
        self.centres = np.stack([camera_to_world(c.cam_from_meta.numpy())[:, 3] for c in cameras]) if cameras else np.zeros((0, 3))
        self.pose: Sim3 | None = None  # meta -> dataparser at the last cull (numpy)
        self.depths = np.zeros(len(cameras))  # median depth of the Gaussians each camera saw then
        self.subset = reference
        self.culls = 0
        self.held = False

    def for_pose(self, meta_to_dataparser: Sim3) -> ReferenceModel:
        """The culled model for rendering the photos under `meta_to_dataparser` (torch or numpy Sim3); inside
        `held_at`, the model culled at the held pose."""
        if self.held:
            return self.subset
        pose = meta_to_dataparser.numpy()
        if self.pose is None or self.moved_far(pose):
            self.cull(pose)
        return self.subset

    @contextmanager
    def held_at(self, meta_to_dataparser: Sim3) -> Iterator[None]:
        """Within it every render uses the model culled (and coarsened) at exactly this pose, whatever pose it is for.

        For poses whose views stay inside the widened frusta of this one, which the caller ensures
        (`optimize.held_for_probes`: the verdict's probes, one teacher cell around the result). Without it, probes in opposite directions each moved
        the cull (a probe's shift is about one cell's angle times the depth, 3% for fast-cpu, at MAX_SHIFT), and on
        a reference of millions of Gaussians each cull merges the level of detail again (seconds), and each probe
        was compared with the result under a model merged at another pose."""
        pose = meta_to_dataparser.numpy()
        if self.pose is None or not np.array_equal(self.pose.matrix, pose.matrix):
            self.cull(pose)
        self.held = True
        try:
            yield
        finally:
            self.held = False

    def moved_far(self, pose: Sim3) -> bool:
        relative = pose @ self.pose.inverse()
        if relative.rotation_angle_deg() > MAX_ROTATION_DEG:
            return True
        shifts = np.linalg.norm(pose.apply(self.centres) - self.pose.apply(self.centres), axis=1)
        return bool(np.any(shifts > MAX_SHIFT * self.depths))

    @torch.no_grad()
    def cull(self, pose: Sim3) -> None:
        means, covars = self.reference.means, self.reference.covars
        depths = torch.empty(len(self.cameras), means.shape[0], device=means.device)
        inside = torch.zeros(len(self.cameras), means.shape[0], dtype=torch.bool, device=means.device)
        on_torch = pose.to_torch()
        for index, camera in enumerate(self.cameras):
            view = viewmat(on_torch.move_camera(camera.cam_from_meta)).float()[None].to(means.device)
            wide = camera.K.clone()[None].to(means.device)
            wide[:, 0, 0] /= WIDEN
            wide[:, 1, 1] /= WIDEN
            camera_depths, camera_inside = cull_gaussians(means, covars, view, wide, camera.width, camera.height, near_plane=CULL_NEAR)
            depths[index], inside[index] = camera_depths[0], camera_inside[0]
            seen = camera_depths[0][camera_inside[0]]
            self.depths[index] = float(seen.median()) if seen.numel() else float("inf")
        ids = torch.nonzero(inside.any(dim=0)).squeeze(1)
        self.pose = pose
        self.subset = self.reference.subset(ids)
        if self.level_of_detail > 0 and ids.numel():
            focal = torch.stack([camera.K[:2, :2].diagonal().max() for camera in self.cameras]).float().to(means.device)
            self.subset = self.coarsened(self.subset, footprint_cells(depths[:, ids], focal, inside[:, ids], 1.0))
        self.culls += 1

    def coarsened(self, culled: ReferenceModel, pixel_cells: Tensor) -> ReferenceModel:
        """`culled` merged per voxel of `level_of_detail` render pixels, doubled while the result holds more than
        `render_budget` Gaussians (at most `MAX_VOXEL_DOUBLINGS` times). `pixel_cells`: [N] one render pixel at the
        nearest photo that sees each Gaussian, scene units (`footprint_cells` at 1 pixel). Each voxel size is only
        planned (a plan's count is the merged model's), and the model merged once, at the size chosen: the merge is
        the costly part (about 2.9 s of a 1M-Gaussian cull, its plan 0.1 s)."""
        pixels = self.level_of_detail
        plan = plan_merge(culled.means, culled.covars, pixel_cells * pixels)
        for _ in range(MAX_VOXEL_DOUBLINGS):
            if self.render_budget <= 0 or plan.count <= self.render_budget:
                break
            pixels *= 2.0
            plan = plan_merge(culled.means, culled.covars, pixel_cells * pixels)
        self.voxel_pixels = pixels
        return merge(culled, plan)
