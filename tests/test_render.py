"""The CPU rasterizer against gsplat's pure-torch projection, a dense reference compositor, and gradcheck."""

from __future__ import annotations

import pytest
import torch
from gsplat.cuda._torch_impl import _fully_fused_projection, _spherical_harmonics

from sg_nerfstudio.render import rasterize, resolve_backend
from sg_nerfstudio.render.cpu_rasterizer import brute_force_composite
from sg_nerfstudio.render.projection import (
    covariances_from_quats_scales,
    cull_gaussians,
    project_gaussians,
    project_gaussians_packed,
)

CPU_BACKENDS = ("numba", "torch")  # tile compositor (default) and the pure-torch pair compositor


def random_scene(n: int, seed: int, channels: int = 4, dtype=torch.float32, spread: float = 1.0):
    """Gaussians scattered in front of (and some behind / beside) a camera at the origin looking +z."""
    gen = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=gen, dtype=dtype) * torch.tensor([spread, 0.8 * spread, 1.0], dtype=dtype)
    means[:, 2] += 3.0
    quats = torch.randn(n, 4, generator=gen, dtype=dtype)
    scales = torch.exp(torch.randn(n, 3, generator=gen, dtype=dtype) * 0.4 - 2.5)
    opacities = torch.rand(n, generator=gen, dtype=dtype) * 0.8 + 0.1
    colors = torch.rand(n, channels, generator=gen, dtype=dtype)
    return means, quats, scales, opacities, colors


def look_at_viewmats(n_cams: int, seed: int, dtype=torch.float32) -> torch.Tensor:
    """World-to-camera matrices of cameras near the origin, slightly rotated, looking roughly along +z."""
    gen = torch.Generator().manual_seed(seed)
    mats = []
    for _ in range(n_cams):
        axis_angle = torch.randn(3, generator=gen, dtype=dtype) * 0.1
        rot = torch.linalg.matrix_exp(torch.tensor(
            [[0, -axis_angle[2], axis_angle[1]], [axis_angle[2], 0, -axis_angle[0]], [-axis_angle[1], axis_angle[0], 0]],
            dtype=dtype,
        ))
        mat = torch.eye(4, dtype=dtype)
        mat[:3, :3] = rot
        mat[:3, 3] = torch.randn(3, generator=gen, dtype=dtype) * 0.1
        mats.append(mat)
    return torch.stack(mats)


def intrinsics(n_cams: int, width: int, height: int, focal: float, dtype=torch.float32) -> torch.Tensor:
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    return K.expand(n_cams, 3, 3).clone()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_projection_matches_gsplat_reference(seed):
    means, quats, scales, _, _ = random_scene(500, seed, spread=2.5)
    means[:20, 2] = -means[:20, 2]  # some behind the camera
    viewmats = look_at_viewmats(3, seed)
    Ks = intrinsics(3, 40, 30, 35.0)
    covars = covariances_from_quats_scales(quats, scales)
    ours = project_gaussians(means, covars, viewmats, Ks, 40, 30, near_plane=0.2, calc_compensations=True)
    radii, means2d, depths, conics, compensations = _fully_fused_projection(
        means, covars, viewmats, Ks, 40, 30, near_plane=0.2, calc_compensations=True
    )
    assert torch.equal(ours.radii, radii)
    valid = radii > 0
    assert 0 < int(valid.sum()) < valid.numel()  # the scene exercises culling both ways
    torch.testing.assert_close(ours.means2d[valid], means2d[valid], rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(ours.depths, depths)
    torch.testing.assert_close(ours.conics[valid], conics[valid], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(ours.compensations[valid], compensations[valid], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("seed", [0, 1])
def test_cheap_cull_keeps_every_visible_gaussian_and_packed_projection_matches(seed):
    means, quats, scales, _, _ = random_scene(800, seed, spread=4.0)
    means[:30, 2] = -means[:30, 2]  # some behind the camera
    scales[:40] *= 8.0  # large ones whose centres are off-screen but whose footprint is not
    viewmats, Ks = look_at_viewmats(3, seed), intrinsics(3, 40, 30, 35.0)
    covars = covariances_from_quats_scales(quats, scales)
    dense = project_gaussians(means, covars, viewmats, Ks, 40, 30, near_plane=0.2)
    depths, candidates = cull_gaussians(means, covars, viewmats, Ks, 40, 30, near_plane=0.2)
    visible = dense.radii > 0
    assert bool(candidates[visible].all())  # a superset of the exact test
    assert int(candidates.sum()) < candidates.numel()  # that still culls
    torch.testing.assert_close(depths, dense.depths)
    cameras, ids = torch.nonzero(candidates, as_tuple=True)
    packed = project_gaussians_packed(means[ids], covars[ids], viewmats, Ks, cameras, 40, 30, near_plane=0.2)
    assert torch.equal(packed.radii, dense.radii[cameras, ids])
    torch.testing.assert_close(packed.means2d, dense.means2d[cameras, ids])
    torch.testing.assert_close(packed.conics, dense.conics[cameras, ids])
    _, _, info = rasterize(means, quats, scales, torch.full((800,), 0.5), torch.rand(800, 3), viewmats, Ks, 40, 30, near_plane=0.2)
    assert torch.equal(info["radii"], dense.radii)


def dense_reference(means, quats, scales, opacities, colors, viewmat, K, width, height, **kw):
    covars = covariances_from_quats_scales(quats, scales)
    proj = project_gaussians(means, covars, viewmat[None], K[None], width, height, **kw)
    visible = proj.radii[0] > 0
    return brute_force_composite(
        proj.means2d[0, visible], proj.conics[0, visible], opacities[visible], colors[visible],
        proj.depths[0, visible], width, height,
    )


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_image_matches_brute_force_compositor(seed, backend):
    means, quats, scales, opacities, colors = random_scene(300, seed, channels=7)
    viewmats = look_at_viewmats(2, seed)
    Ks = intrinsics(2, 24, 18, 20.0)
    render, alphas, info = rasterize(means, quats, scales, opacities, colors, viewmats, Ks, 24, 18, backend=backend)
    assert render.shape == (2, 18, 24, 7) and alphas.shape == (2, 18, 24, 1)
    for cam in range(2):
        ref_render, ref_alpha = dense_reference(means, quats, scales, opacities, colors, viewmats[cam], Ks[cam], 24, 18)
        torch.testing.assert_close(render[cam], ref_render, rtol=1e-5, atol=2e-6)
        torch.testing.assert_close(alphas[cam], ref_alpha, rtol=1e-5, atol=2e-6)
    assert alphas.max() > 0.9  # opaque enough that the early stop is exercised
    assert info["radii"].shape == (2, 300) and info["means2d"].shape == (2, 300, 2)
    assert info["width"] == 24 and info["height"] == 18 and info["n_cameras"] == 2


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_depth_modes_background_and_antialiasing(backend):
    means, quats, scales, opacities, colors = random_scene(200, 5, channels=3)
    viewmats, Ks = look_at_viewmats(1, 5), intrinsics(1, 20, 16, 18.0)
    args = (means, quats, scales, opacities, colors, viewmats, Ks, 20, 16)
    rgbd, alpha, _ = rasterize(*args, render_mode="RGB+D", backend=backend)
    depth, _, _ = rasterize(*args, render_mode="D", backend=backend)
    expected_depth, _, _ = rasterize(*args, render_mode="ED", backend=backend)
    torch.testing.assert_close(rgbd[..., 3:], depth)
    torch.testing.assert_close(expected_depth, depth / alpha.clamp(min=1e-10))
    covered = alpha[..., 0] > 0.5
    assert ((expected_depth[..., 0][covered] > 0.5) & (expected_depth[..., 0][covered] < 8.0)).all()

    background = torch.tensor([[0.2, 0.4, 0.9]])
    rgb_bg, _, _ = rasterize(*args, backgrounds=background, backend=backend)
    torch.testing.assert_close(rgb_bg, rgbd[..., :3] + (1 - alpha) * background[:, None, None, :])

    aa, _, info = rasterize(*args, rasterize_mode="antialiased", backend=backend)
    covars = covariances_from_quats_scales(quats, scales)
    proj = project_gaussians(means, covars, viewmats, Ks, 20, 16, calc_compensations=True)
    visible = proj.radii[0] > 0
    ref, _ = brute_force_composite(
        proj.means2d[0, visible], proj.conics[0, visible], (opacities * proj.compensations[0])[visible],
        colors[visible], proj.depths[0, visible], 20, 16,
    )
    torch.testing.assert_close(aa[0], ref, rtol=1e-5, atol=2e-6)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_spherical_harmonics_colours_match_gsplat_basis(backend):
    means, quats, scales, opacities, _ = random_scene(150, 9)
    coeffs = torch.randn(150, 16, 3, generator=torch.Generator().manual_seed(9)) * 0.3
    viewmats, Ks = look_at_viewmats(1, 9), intrinsics(1, 16, 12, 14.0)
    for degree in (0, 1, 2, 3):
        render, _, _ = rasterize(means, quats, scales, opacities, coeffs, viewmats, Ks, 16, 12, sh_degree=degree, backend=backend)
        centre = -viewmats[0, :3, :3].T @ viewmats[0, :3, 3]
        colors = torch.clamp_min(_spherical_harmonics(degree, means - centre, coeffs) + 0.5, 0.0)
        ref, _ = dense_reference(means, quats, scales, opacities, colors, viewmats[0], Ks[0], 16, 12)
        torch.testing.assert_close(render[0], ref, rtol=1e-5, atol=2e-6)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_gradcheck_all_gaussian_parameters_and_viewmats(backend):
    dtype = torch.float64
    means, quats, scales, opacities, colors = random_scene(6, 11, channels=2, dtype=dtype, spread=0.4)
    scales = scales * 3.0  # a few pixels wide at this resolution
    viewmats, Ks = look_at_viewmats(1, 11, dtype=dtype), intrinsics(1, 10, 8, 9.0, dtype=dtype)
    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, opacities, colors, viewmats)]

    def render(m, q, s, o, c, v):
        image, alpha, _ = rasterize(m, q, s, o, c, v, Ks, 10, 8, render_mode="RGB+ED", backend=backend)
        return image, alpha

    image, alpha = render(*inputs)
    assert alpha.max() > 0.3 and (alpha == 0).any()  # covered and uncovered pixels
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_pose_only_gradient_matches_full_gradient(backend):
    means, quats, scales, opacities, colors = random_scene(400, 4, channels=5)
    viewmats, Ks = look_at_viewmats(2, 4), intrinsics(2, 20, 16, 18.0)
    weights = torch.randn(2, 16, 20, 5, generator=torch.Generator().manual_seed(0))

    def pose_grad(params_require_grad: bool) -> torch.Tensor:
        params = [t.clone().requires_grad_(params_require_grad) for t in (means, quats, scales, opacities, colors)]
        pose = viewmats.clone().requires_grad_(True)
        render, _, _ = rasterize(*params, pose, Ks, 20, 16, backend=backend)
        (render * weights).sum().backward()
        return pose.grad

    # frozen Gaussians take the compiled projection (float64 inside), trainable ones autograd in float32
    torch.testing.assert_close(pose_grad(False), pose_grad(True), rtol=1e-5, atol=1e-5)
    assert pose_grad(False).abs().sum() > 0


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_degenerate_scenes_give_background_and_finite_gradients(backend):
    means, quats, scales, opacities, colors = random_scene(40, 3, channels=3)
    means[:10, 2] = -2.0  # behind the camera
    means[10:20, 0] = 50.0  # far outside the image
    means[20:30, 2] = 0.0  # in the camera plane
    opacities[30:] = 0.0  # invisible
    viewmats, Ks = look_at_viewmats(1, 3), intrinsics(1, 12, 10, 10.0)
    background = torch.tensor([[0.3, 0.5, 0.7]])
    for scene in ((means, quats, scales, opacities, colors), tuple(t[:0] for t in (means, quats, scales, opacities, colors))):
        params = [t.clone().requires_grad_(True) for t in scene]
        pose = viewmats.clone().requires_grad_(True)
        render, alpha, info = rasterize(*params, pose, Ks, 12, 10, backgrounds=background, render_mode="RGB+ED", backend=backend)
        assert torch.all(alpha == 0)
        torch.testing.assert_close(render[..., :3], background[:, None, None, :].expand(1, 10, 12, 3))
        assert torch.isfinite(render).all()
        (render.sum() + alpha.sum()).backward()
        for tensor in (*params, pose):
            assert tensor.grad is not None and torch.isfinite(tensor.grad).all()
        assert info["means2d"].shape == (1, scene[0].shape[0], 2)
        assert torch.isfinite(info["means2d"][:, 10:]).all()


def test_backend_selection_and_input_checks():
    assert resolve_backend("auto", torch.device("cpu")) == "numba"
    assert resolve_backend("torch", torch.device("cpu")) == "torch"
    with pytest.raises(RuntimeError, match="backend='gsplat' needs CUDA"):
        resolve_backend("gsplat", torch.device("cpu"))
    means, quats, scales, opacities, colors = random_scene(5, 0)
    viewmats, Ks = look_at_viewmats(1, 0), intrinsics(1, 8, 8, 8.0)
    with pytest.raises(ValueError, match="quats must be"):
        rasterize(means, quats[:4], scales, opacities, colors, viewmats, Ks, 8, 8)
    with pytest.raises(ValueError, match="render_mode"):
        rasterize(means, quats, scales, opacities, colors, viewmats, Ks, 8, 8, render_mode="RGBD")
    with pytest.raises(ValueError, match="absgrad"):
        rasterize(means, quats, scales, opacities, colors, viewmats, Ks, 8, 8, absgrad=True)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_default_strategy_densifies_with_cpu_info(backend):
    """gsplat's DefaultStrategy (what splatfacto uses) runs unchanged on the CPU backend's info."""
    from gsplat.strategy import DefaultStrategy

    means, quats, scales, opacities, colors = random_scene(300, 6, channels=3)
    params = torch.nn.ParameterDict({
        "means": means, "quats": quats, "scales": torch.log(scales),
        "opacities": torch.logit(opacities), "colors": colors,
    })
    optimizers = {name: torch.optim.Adam([p], lr=1e-3) for name, p in params.items()}
    strategy = DefaultStrategy(refine_start_iter=2, refine_every=3, reset_every=1000, grow_grad2d=1e-9, verbose=False)
    state = strategy.initialize_state()
    viewmats, Ks = look_at_viewmats(1, 6), intrinsics(1, 24, 18, 20.0)
    for step in range(6):
        render, _, info = rasterize(
            params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
            params["colors"], viewmats, Ks, 24, 18, backend=backend,
        )
        strategy.step_pre_backward(params, optimizers, state, step, info)
        render.mean().backward()
        assert info["means2d"].grad is not None
        strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad()
    assert len(params["means"]) > 300
    assert all(len(p) == len(params["means"]) for p in params.values())


def test_threads_setting_sizes_torch_and_numba_pools():
    import numba

    from sg_nerfstudio.render.threads import ThreadCountError, available_cores, set_threads

    before = (torch.get_num_threads(), numba.get_num_threads())
    try:
        assert set_threads(1) == 1
        assert (torch.get_num_threads(), numba.get_num_threads()) == (1, 1)
        assert set_threads(None) == available_cores() >= 1
        assert torch.get_num_threads() == available_cores()
        for wrong in (0, -1):  # COLMAP's "-1: all cores" is not ours: one sentence, the pools as they were
            with pytest.raises(ThreadCountError, match=f"--threads must be 1 or more .*, got {wrong}\\."):
                set_threads(wrong)
            assert torch.get_num_threads() == available_cores()
    finally:
        torch.set_num_threads(before[0])
        numba.set_num_threads(before[1])


def test_the_suite_runs_on_the_pinned_cpu_code_paths():
    """tests/conftest.py pins each library's CPU dispatch before torch and numba load (its CPU_PINS): an import moved
    above the pins would leave them unread, and the tiny reference another draw on another machine."""
    import numba
    from conftest import CPU_PINS, PINNED

    if not PINNED:
        pytest.skip("this CPU lacks some of haswell's instructions: the suite runs on its own code paths")
    assert torch.backends.cpu.get_cpu_capability() == CPU_PINS["ATEN_CPU_CAPABILITY"].upper()
    assert numba.config.CPU_NAME == CPU_PINS["NUMBA_CPU_NAME"] and numba.config.CPU_FEATURES == CPU_PINS["NUMBA_CPU_FEATURES"]


@pytest.mark.parametrize(
    "given, expected",
    [
        ({}, ("1000", "0", None)),
        ({"OMP_WAIT_POLICY": "PASSIVE"}, (None, None, "PASSIVE")),
        ({"GOMP_SPINCOUNT": "50"}, ("50", "0", None)),
    ],
)
def test_importing_the_package_bounds_the_openmp_spin_unless_the_user_chose(given, expected):
    """A fresh interpreter (the variables only count before torch starts OpenMP): the import sets a spin count of
    1000 (GNU OpenMP) and a block time of 0 (Intel / LLVM OpenMP) where the user set no wait policy, and leaves a
    user's choice alone."""
    import os
    import subprocess
    import sys

    names = ("GOMP_SPINCOUNT", "KMP_BLOCKTIME", "OMP_WAIT_POLICY")
    env = {key: value for key, value in os.environ.items() if key not in names}
    code = f"import os, sg_nerfstudio; print(*(os.environ.get(name) for name in {names}))"
    out = subprocess.run([sys.executable, "-c", code], env={**env, **given}, capture_output=True, text=True, check=True).stdout.split()
    assert tuple(None if value == "None" else value for value in out) == expected


@pytest.mark.parametrize("seed", [0, 1])
def test_frozen_projection_matches_autograd_projection_and_its_camera_gradients(seed):
    """The compiled projection of a frozen model (registration) gives the outputs and viewmat gradients of
    `project_gaussians_packed` through autograd, clamped (off-screen) and near-plane entries included."""
    from sg_nerfstudio.render.frozen_projection import project_frozen_packed

    means, quats, scales, _, _ = random_scene(400, seed, dtype=torch.float64, spread=3.0)
    means[:10, 2] = 0.05  # close to the camera plane
    covars = covariances_from_quats_scales(quats, scales)
    viewmats = look_at_viewmats(3, seed, dtype=torch.float64)
    Ks = intrinsics(3, 40, 30, 35.0, dtype=torch.float64)
    camera_ids = torch.arange(3).repeat_interleave(torch.tensor([150, 150, 100]))
    weights = [torch.randn(400, k, generator=torch.Generator().manual_seed(seed + k), dtype=torch.float64) for k in (2, 3, 3, 1)]

    def outputs_and_grad(project):
        cameras = viewmats.clone().requires_grad_(True)
        proj = project(means, covars, cameras, Ks, camera_ids, 40, 30, near_plane=0.1)
        fields = (proj.means2d, proj.conics, proj.cov2d, proj.depths[:, None])
        loss = sum((field * weight).sum() for field, weight in zip(fields, weights))
        (grad,) = torch.autograd.grad(loss, cameras)
        return proj, grad

    ours, our_grad = outputs_and_grad(project_frozen_packed)
    theirs, their_grad = outputs_and_grad(project_gaussians_packed)
    for name in ("means2d", "conics", "cov2d", "depths"):
        torch.testing.assert_close(getattr(ours, name), getattr(theirs, name), rtol=1e-9, atol=1e-9)
    assert torch.equal(ours.radii, theirs.radii)
    assert (theirs.radii == 0).any() and (theirs.radii > 0).any()
    torch.testing.assert_close(our_grad, their_grad, rtol=1e-7, atol=1e-7)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_frozen_sh_colours_match_autograd_and_their_camera_gradients(degree):
    """SH colours of a frozen model towards each entry's camera, and the gradient for the camera centres, as
    `rasterization._entry_colors` gives them through autograd (some colours clamped at 0 included)."""
    from sg_nerfstudio.render.frozen_projection import frozen_sh_colors
    from sg_nerfstudio.render.rasterization import _entry_colors

    generator = torch.Generator().manual_seed(degree)
    means = torch.randn(300, 3, generator=generator, dtype=torch.float64)
    coeffs = torch.randn(300, 16, 3, generator=generator, dtype=torch.float64) * 2.0
    viewmats = look_at_viewmats(3, degree, dtype=torch.float64)
    gaussian_ids = torch.randint(0, 300, (500,), generator=generator)
    camera_ids = torch.randint(0, 3, (500,), generator=generator).sort().values
    weights = torch.randn(500, 3, generator=generator, dtype=torch.float64)

    cameras = viewmats.clone().requires_grad_(True)
    theirs = _entry_colors(coeffs, degree, means, cameras, gaussian_ids, camera_ids)
    if theirs.requires_grad:
        (their_grad,) = torch.autograd.grad((theirs * weights).sum(), cameras)
    else:  # degree 0: the colour does not depend on the direction
        their_grad = torch.zeros_like(viewmats)
    cameras = viewmats.clone().requires_grad_(True)
    rotations, translations = cameras[:, :3, :3], cameras[:, :3, 3]
    centres = -(rotations.transpose(1, 2) @ translations[:, :, None])[:, :, 0]
    ours = frozen_sh_colors(means, coeffs, centres, gaussian_ids, camera_ids, degree)
    (our_grad,) = torch.autograd.grad((ours * weights).sum(), cameras)
    torch.testing.assert_close(ours, theirs, rtol=1e-10, atol=1e-12)
    assert (theirs == 0).any()
    torch.testing.assert_close(our_grad, their_grad, rtol=1e-8, atol=1e-10)


def test_frozen_kernels_read_a_float32_model_without_losing_float64_arithmetic():
    """A float32 model (as registration loads it) is read in place, yet the kernels compute in float64: the
    outputs equal the float64 computation on the same values rounded once to float32, and the camera gradients
    equal it to float64 precision."""
    from sg_nerfstudio.render.frozen_projection import frozen_sh_colors, project_frozen_packed

    means, quats, scales, _, _ = random_scene(300, 3, dtype=torch.float64, spread=3.0)
    covars = covariances_from_quats_scales(quats, scales).float().double()
    means = means.float().double()
    coeffs = (torch.randn(300, 16, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 2.0).float().double()
    viewmats = look_at_viewmats(2, 3, dtype=torch.float64).float().double()
    Ks = intrinsics(2, 40, 30, 35.0, dtype=torch.float64)
    camera_ids = torch.arange(2).repeat_interleave(150)
    gaussian_ids = torch.arange(300)

    centres = -(viewmats[:, :3, :3].transpose(1, 2) @ viewmats[:, :3, 3:])[:, :, 0].float().double()

    def run(dtype):
        cameras, eyes = viewmats.to(dtype).requires_grad_(True), centres.to(dtype).requires_grad_(True)
        proj = project_frozen_packed(means.to(dtype), covars.to(dtype), cameras, Ks.to(dtype), camera_ids, 40, 30, near_plane=0.1)
        colours = frozen_sh_colors(means.to(dtype), coeffs.to(dtype), eyes, gaussian_ids, camera_ids, 3)
        loss = proj.means2d.sum() + proj.conics.sum() + proj.depths.sum() + colours.sum()
        grads = torch.autograd.grad(loss, (cameras, eyes))
        return (proj.means2d, proj.conics, proj.cov2d, proj.depths, colours), grads

    single, single_grads = run(torch.float32)
    double, double_grads = run(torch.float64)
    for ours, exact in zip(single, double):
        assert ours.dtype == torch.float32
        assert torch.equal(ours, exact.float())
    for ours, exact in zip(single_grads, double_grads):
        assert ours.dtype == torch.float32
        torch.testing.assert_close(ours.double(), exact, rtol=1e-5, atol=1e-5)
