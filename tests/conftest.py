"""Shared fixtures: the tiny synthetic scene and a small sg-feature-splat trained on it (once per session)."""

from __future__ import annotations

import os
import platform
from pathlib import Path

CPU_PINS = {
    "ATEN_CPU_CAPABILITY": "avx2",  # torch's vectorised kernels (an AVX-512 machine picks its own by default)
    "ONEDNN_MAX_CPU_ISA": "AVX2",  # oneDNN's convolutions (the teacher's filters, SSIM, the 1x1 decoder)
    "MKL_CBWR": "COMPATIBLE",  # MKL's BLAS code path
    "NUMBA_CPU_NAME": "haswell",  # the CPU rasterizer's compiled code: vector width, fused multiply-adds ...
    "NUMBA_CPU_FEATURES": "",  # ... from haswell's own feature set, not the host's
}
"""The code paths every library's CPU dispatch takes in the tests, pinned to AVX2 where the machine has it (set before
torch and numba load, over any value the shell set). Training the tiny reference amplifies last-bit differences:
measured on an AMD EPYC (AVX2, 2026-12-06), torch's `default` kernels, oneDNN held to SSE4.1 or numba's `generic`
CPU each trained another draw (other Gaussian counts and losses), as a machine whose libraries pick AVX-512 may; the
pins below reproduce that machine's own draw bit for bit, the one the tolerances were checked on. numpy's and
OpenCV's dispatch and glibc's libm variants were tried the same way and changed nothing."""


HASWELL_FLAGS = {"avx", "avx2", "fma", "f16c", "bmi1", "bmi2", "abm", "movbe", "popcnt", "sse4_2"}


def cpu_supports_pins() -> bool:
    """x86-64 Linux with haswell's instructions that compiled code may use (read from /proc/cpuinfo: torch and numba
    must not load before the pins): numba's code for haswell would stop at the first one missing."""
    if platform.machine() not in ("x86_64", "AMD64"):
        return False
    try:
        flags = next(line for line in Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("flags")).split()
    except (OSError, StopIteration):
        return False
    return HASWELL_FLAGS <= set(flags)


PINNED = cpu_supports_pins()
if PINNED:
    for name, value in CPU_PINS.items():
        os.environ[name] = value

import pytest  # noqa: E402
import torch  # noqa: E402

from sg_nerfstudio.features import TeacherConfig  # noqa: E402
from sg_nerfstudio.render.threads import set_threads  # noqa: E402
from sg_nerfstudio.scripts.make_scene import main as make_scene_main  # noqa: E402
from sg_nerfstudio.splat.training import cpu_config, save, train  # noqa: E402

TEST_THREADS = 2
"""Every test trains and renders on this many threads (torch's and numba's pools), whatever the machine's cores: the
CPU rasterizer's per-worker gradient sums and torch's parallel reductions follow the thread count, and the tiny
reference trained on another count is another draw. With one thread (`OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1`) four
accuracy tests missed their tolerances (2026-12-06). 2 is the CI machine's count, on which the tolerances were set.
numba's pool cannot grow past NUMBA_NUM_THREADS (the cores, by default): a one-core machine still runs one."""


def pytest_configure(config):
    set_threads(TEST_THREADS)  # before any fixture: the session's tiny reference trains on them


def pytest_report_header(config):
    import numba

    paths = f"torch {torch.backends.cpu.get_cpu_capability()}, numba {numba.config.CPU_NAME or 'host'}"
    if not PINNED:
        return f"CPU code paths not pinned (this CPU lacks some of HASWELL_FLAGS): {paths}; the tiny reference may be another draw"
    return f"CPU code paths pinned (tests/conftest.py CPU_PINS): {paths}; {TEST_THREADS} threads"


@pytest.fixture(autouse=True)
def pinned_threads(monkeypatch):
    """Both pools at TEST_THREADS for each test, and the commands' default (`--threads` unset: every core) too."""
    for module in ("sg_nerfstudio.render.threads", "sg_nerfstudio.scripts.meta_images"):
        monkeypatch.setattr(f"{module}.available_cores", lambda: TEST_THREADS)
    set_threads(TEST_THREADS)


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    output = tmp_path_factory.mktemp("scenes") / "tiny"
    assert make_scene_main(["--preset", "tiny", "--output", str(output), "--occluder-rate", "0.6"]) == 0
    return output


def make_config(data: Path, output: Path, steps: int, teacher: TeacherConfig):
    """A short CPU run whose densification and resolution schedule happen within `steps`."""
    config = cpu_config(data, output, steps, teacher)
    config.machine.seed = 0
    model = config.pipeline.model
    model.warmup_length, model.refine_every, model.reset_alpha_every = 60, 60, 1000
    model.resolution_schedule = 100
    model.feature_render_scale = 1.5  # the tiny scene's 48 px images: features apart at 1.5 x the 16-cell grid, 24 px
    return config


@pytest.fixture(scope="session")
def trained(tiny_scene, tmp_path_factory):
    """A 300-step CPU sg-feature-splat of the tiny scene (offline teacher): (trainer, loss history, config)."""
    output = tmp_path_factory.mktemp("train")
    config = make_config(tiny_scene / "reference", output, 300, TeacherConfig(name="offline", input_size=128, cache_dir=output / "cache"))
    history = []
    trainer = train(config, lambda step, trainer, losses: history.append(
        {name: float(value.detach()) for name, value in losses.items()} | {"n": trainer.pipeline.model.num_points}
    ))
    save(trainer, config)
    return trainer, history, config


@pytest.fixture(scope="session")
def quick_trained(tiny_scene, tmp_path_factory) -> Path:
    """The config.yml of a 20-step CPU sg-feature-splat of the tiny scene (a few seconds): a trained run on disk, as
    ns-train leaves one, for tests of what reads it (the viewer) that need no accuracy from the model."""
    output = tmp_path_factory.mktemp("quick-train")
    config = make_config(tiny_scene / "reference", output, 20, TeacherConfig(name="offline", input_size=128, cache_dir=output / "cache"))
    save(train(config, lambda step, trainer, losses: None), config)
    return config.get_base_dir() / "config.yml"


SLOW_FIXTURES = {
    "trained": "the session's 300-step tiny reference: ~10 s of training, and the ~90 tests on it take ~5 min together",
}
"""A test that uses one of these fixtures, directly or through another fixture, is marked `slow`: `pytest -m "not slow"`
leaves it out. A new test is classified by the fixtures it asks for; SLOW_TESTS names the rest."""

SLOW_TESTS = {
    "tests/test_bench.py::test_sg_bench_writes_tables_and_resumes": "trains the benchmark's references, runs sg-bench: ~70 s",
    "tests/test_bench.py::test_benchmark_modules_end_a_missing_reference_with_one_sentence[scaling-arguments1]":
        "python -m sg_nerfstudio.bench.scaling and its measurement child: two interpreters importing torch, ~5 s",
    "tests/test_install.py::test_sg_demo_runs_from_a_non_editable_install_outside_the_repository": "a wheel and sg-demo: ~40 s",
    "tests/test_photos.py::test_retrieval_pairs_above_the_exhaustive_limit": "SfM with retrieval pairs: ~20 s",
    "tests/test_initialisers.py::test_initialisers_recover_the_ground_truth_on_clean_renders": "~6 s each",
    "tests/test_initialisers.py::test_photos_too_weak_to_register_alone_lend_their_rig_inliers_as_anchors": "~8 s",
    "tests/test_render.py::test_gradcheck_all_gaussian_parameters_and_viewmats[numba]": "float64 gradcheck through numba: ~10 s",
    "tests/test_dense_init.py::test_auto_falls_back_to_the_dense_start_where_sift_gives_none": "a small gap scene, SIFT and the dense start: ~17 s",
    "tests/test_gap_scenes.py::test_a_gap_scene_holds_its_photo_render_pairs_and_their_gap_measure": "a gap scene and its gap measure: ~11 s",
    "tests/test_photos.py::test_a_coarse_model_reference_renders_the_photos_model_and_holds_measured_pairs":
        "trains a coarse model, SfM and SIFT on its renders: ~25 s",
}
"""Tests slow on their own, over ~3 s on the 2-core CI machine (2026-12-06, numba's cache warm): node id -> why. An id
without parameters marks every parametrisation. tests/test_lint.py checks that each still names a test."""


def pytest_collection_modifyitems(config, items):
    for item in items:
        if set(SLOW_FIXTURES) & set(getattr(item, "fixturenames", ())) or {item.nodeid, item.nodeid.split("[")[0]} & set(SLOW_TESTS):
            item.add_marker(pytest.mark.slow)
