"""The CUDA path: the frozen reference rendered by gsplat and registered on CUDA tensors.

Runs only where CUDA exists (gsplat's rasterizer has no CPU kernels); everywhere else the same registration is
tested on the CPU rasterizer (tests/test_register.py).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sg_nerfstudio.geometry.meta_image import load_meta_image
from sg_nerfstudio.geometry.sim3 import Sim3, perturbed
from sg_nerfstudio.registration.metrics import pose_errors
from sg_nerfstudio.registration.objectives import PhotoLosses, build_objective, prepare_photos
from sg_nerfstudio.registration.optimize import register
from sg_nerfstudio.registration.reference import load_reference
from sg_nerfstudio.registration.settings import RegistrationSettings
from sg_nerfstudio.render.rasterization import gsplat_available

pytestmark = pytest.mark.skipif(not gsplat_available(), reason="needs CUDA and gsplat (gsplat's rasterizer has no CPU kernels)")

SETTINGS = RegistrationSettings().changed(optimiser={"steps": 60, "lr": 0.004, "lr_final": 0.0002}, objective={"render_scale": 2.0, "kind": "teacher-on-render"}, seed=0)


@pytest.fixture(scope="module")
def scene(trained, tiny_scene):
    _, _, config = trained
    meta = load_meta_image(tiny_scene / "meta" / "front")
    truth = Sim3.read_json(tiny_scene / "meta" / "front" / "gt_transform.json", "Ground truth")
    return config.get_base_dir() / "config.yml", meta, truth


def test_gsplat_losses_on_cuda_match_the_cpu_rasterizer(scene):
    config, meta, truth = scene
    values = {}
    for device in ("cpu", "cuda"):
        reference = load_reference(config, device=device)
        assert reference.means.device.type == device
        objective = build_objective(reference, SETTINGS)
        photos = prepare_photos(reference, meta, SETTINGS, objective)
        losses = PhotoLosses(reference, photos, objective, SETTINGS, 0.01)
        with torch.no_grad():
            per_photo, coverage = losses((reference.world_to_dataparser @ truth).to_torch(), list(range(len(photos))))
        values[device] = (torch.stack(per_photo).cpu(), coverage)
    torch.testing.assert_close(values["cuda"][0], values["cpu"][0], rtol=0.02, atol=1e-3)
    torch.testing.assert_close(values["cuda"][1], values["cpu"][1], rtol=0.02, atol=1e-3)


def test_registration_on_cuda_tensors_moves_towards_the_truth(scene):
    config, meta, truth = scene
    reference = load_reference(config, device="cuda")
    start = perturbed(truth, meta.centres, np.random.default_rng(3), 3.0, 0.03, 0.03)
    result = register(reference, meta, start, SETTINGS)
    assert np.isfinite(result.final_losses).all()
    assert result.final_trimmed_loss < float(np.median(result.initial_losses))
    assert pose_errors(meta.poses, result.transform, truth).rotation_deg < pose_errors(meta.poses, start, truth).rotation_deg
