"""A weight-free dense descriptor from a maintained library: kornia's differentiable dense RootSIFT.

One 128-d SIFT descriptor (8 orientations x 4 x 4 spatial bins, clipped, RootSIFT-normalised) per cell of
`CELL` pixels of the image resized to `input_size` on its long side (aspect ratio kept), centred on the cell,
spanning 4 x 4 bins of `SPATIAL_BIN` pixels. Where the offline descriptor (`offline.py`) pools orientation
histograms over whole cells at three scales, SIFT keeps *where* inside its support each orientation occurs:
more discriminative, narrower in what it tolerates. It is computed on the mean of the log colour channels,
so a global exposure gain and per-channel white balance add constants the gradients remove, and RootSIFT's
normalisation removes the gradient scale a gamma curve leaves (as for the offline descriptor).

`kornia.feature.DenseSIFTDescriptor` supplies the gradients, the soft orientation binning, the bin pooling
kernel and the bins-to-descriptor kernel. Its forward pools every orientation map at every pixel and then samples
the pooled maps every `SPATIAL_BIN` pixels (a dilated, strided convolution); here the pooling runs only at those
samples (the same kernels with a stride), which gives the same descriptors (a test compares them with kornia's
module) at a third of the cost: 16 renders of 128 x 96 described on 32 x 24 cells, forward and backward, take
0.19 s, 0.59 s with kornia's module as is and 0.13 s with the offline descriptor (2 threads, median of 5), where
the full-resolution pooling's backward was 70% of the module's time.

Measured as registration's render teacher (docs/measurements.md, "Dense SIFT as the render teacher"): with the keypoint anchors
it ends slightly closer on the real-photo scenes and the same on synthetic ones; the dense objective alone has a
much narrower basin with it. The presets keep the offline descriptor; `--objective.render-teacher dense-sift` selects it.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from sg_nerfstudio.features.base import CellDescriptor, TeacherConfig, TeacherInputError
from sg_nerfstudio.features.offline import LOG_OFFSET  # the same log input as the offline descriptor

CELL = 8
SPATIAL_BIN = 4
SPATIAL_BINS = 4
ANGLE_BINS = 8
DEFAULT_INPUT_SIZE = 256
VERSION = 1


def _kornia_padding() -> int:
    """Padding that centres output (i, j) on cell (i, j): kornia centres it on
    j * stride - padding + (bins - 1) * bin / 2 - e / 2 (e = 1 for an even bin size), the cell centre is
    j * CELL + (CELL - 1) / 2."""
    even = 1 if SPATIAL_BIN % 2 == 0 else 0
    padding = ((SPATIAL_BINS - 1) * SPATIAL_BIN - even - (CELL - 1)) / 2
    assert padding == int(padding) and padding >= 0
    assert CELL == 2 * SPATIAL_BIN and SPATIAL_BINS == 4 and int(padding) == SPATIAL_BIN // 2, "sampled_descriptors assumes these"
    return int(padding)


class DenseSiftTeacher(CellDescriptor):
    """image [H, W, 3] in [0, 1] -> [rows, columns, 128] dense RootSIFT (long side: input_size / 8)."""

    cell, default_input_size, cell_name = CELL, DEFAULT_INPUT_SIZE, "dense SIFT cell size"
    feature_dim = ANGLE_BINS * SPATIAL_BINS**2

    def __init__(self, config: TeacherConfig):
        try:
            from kornia.feature import DenseSIFTDescriptor
        except ImportError:
            raise TeacherInputError("The dense-sift teacher needs kornia (pip install kornia); it is not importable here.") from None
        super().__init__(config)
        self.descriptor = DenseSIFTDescriptor(
            num_ang_bins=ANGLE_BINS, num_spatial_bins=SPATIAL_BINS, spatial_bin_size=SPATIAL_BIN, rootsift=True,
            stride=CELL, padding=_kornia_padding(),
        ).to(self.device)

    def settings(self) -> dict:
        return {"teacher": "dense_sift", "version": VERSION, "input_size": self.input_size, "cell": CELL,
                "spatial_bin": SPATIAL_BIN, "spatial_bins": SPATIAL_BINS, "angle_bins": ANGLE_BINS}

    def describe_resized(self, pixels: Tensor) -> Tensor:
        """[1, 3, 8 rows, 8 columns] -> [1, 128, rows, columns], on the mean of the log colour channels."""
        return self.sampled_descriptors(torch.log(pixels.clamp(min=0.0) + LOG_OFFSET).mean(dim=1, keepdim=True))

    def sampled_descriptors(self, image: Tensor) -> Tensor:
        """kornia's dense SIFT of [B, 1, H, W] (H, W multiples of CELL) at the cell centres: [B, 128, H / 8, W / 8].

        kornia pools each orientation map with a SPATIAL_BIN x SPATIAL_BIN kernel (padding SPATIAL_BIN / 2) at every
        pixel u and reads the pooled maps at u = CELL i + SPATIAL_BIN k - 2 (k = 0..3, zero outside). Those are the
        u = 4 m + 2, whose windows are the input rows 4 m .. 4 m + 3: a stride-4 pooling without padding gives them
        all (m = 0 .. H / 4 - 1), and the bins-to-descriptor kernel then reads m = 2 i + k - 1 (stride 2, padding 1).
        """
        descriptor = self.descriptor
        histograms = descriptor.get_gradient_histograms(image)  # [B, 8, H, W]
        pooling = descriptor.bin_pooling_kernel.weight.detach().to(image).expand(ANGLE_BINS, 1, SPATIAL_BIN, SPATIAL_BIN)
        pooled = F.conv2d(histograms, pooling, stride=SPATIAL_BIN, groups=ANGLE_BINS)  # [B, 8, H / 4, W / 4]
        raw = F.conv2d(pooled, descriptor.PoolingConv.weight.detach().to(image), stride=CELL // SPATIAL_BIN, padding=1)
        clipped = _l2_normalised(raw).clamp(0.0, descriptor.clipval)
        return torch.sqrt(F.normalize(_l2_normalised(clipped), p=1, dim=1) + descriptor.eps)  # RootSIFT


def _l2_normalised(descriptors: Tensor) -> Tensor:
    """Unit length along dim 1; an all-zero descriptor (a flat neighbourhood) stays zero with a zero gradient
    (as in kornia: normalising it would divide by the norm's floor and send gradients of 1e12)."""
    zero = descriptors.abs().amax(dim=1, keepdim=True) == 0
    return torch.where(zero, torch.zeros_like(descriptors), F.normalize(descriptors, dim=1))
