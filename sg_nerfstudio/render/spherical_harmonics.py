"""View-dependent colour from real spherical-harmonic coefficients, in the 3DGS / gsplat basis.

nerfstudio's `components_from_spherical_harmonics` uses other signs for the odd bands, so a splatfacto
checkpoint (trained with gsplat's basis) needs gsplat's basis to look right; gsplat only ships it as a
CUDA kernel plus a private reference function, hence this small module (constants from Sloan,
"Efficient Spherical Harmonic Evaluation", JCGT 2013, as gsplat uses them).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Real SH basis up to `degree` (0..3) at unit directions.

    Args:
        degree: highest band.
        dirs: [..., 3] unit vectors.

    Returns:
        [..., (degree + 1) ** 2] basis values.
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be between 0 and 3, got {degree}.")
    x, y, z = dirs.unbind(-1)
    bands = [torch.full_like(x, 0.2820947917738781)]
    if degree >= 1:
        bands += [-0.48860251190292 * y, 0.48860251190292 * z, -0.48860251190292 * x]
    if degree >= 2:
        z2 = z * z
        c1, s1 = x * x - y * y, 2 * x * y
        bands += [
            0.5462742152960395 * s1,
            -1.092548430592079 * z * y,
            0.9461746957575601 * z2 - 0.3153915652525201,
            -1.092548430592079 * z * x,
            0.5462742152960395 * c1,
        ]
    if degree >= 3:
        c2, s2 = x * c1 - y * s1, x * s1 + y * c1
        tmp_c = -2.285228997322329 * z2 + 0.4570457994644658
        tmp_b = 1.445305721320277 * z
        bands += [
            -0.5900435899266435 * s2,
            tmp_b * s1,
            tmp_c * y,
            z * (1.865881662950577 * z2 - 1.119528997770346),
            tmp_c * x,
            tmp_b * c1,
            -0.5900435899266435 * c2,
        ]
    return torch.stack(bands, dim=-1)


def evaluate_sh(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Colours from SH coefficients, using the first (degree + 1) ** 2 of the K coefficients.

    Args:
        degree: active SH degree.
        dirs: [..., 3] viewing directions (camera centre -> Gaussian), any length.
        coeffs: [..., K, 3] coefficients, K >= (degree + 1) ** 2.

    Returns:
        [..., 3] colours before the +0.5 offset and clamping that rasterization applies.
    """
    n_bases = (degree + 1) ** 2
    if coeffs.shape[-2] < n_bases:
        raise ValueError(f"sh_degree {degree} needs {n_bases} coefficients per channel, got {coeffs.shape[-2]}.")
    basis = sh_basis(degree, F.normalize(dirs, p=2, dim=-1))
    return (basis[..., None] * coeffs[..., :n_bases, :]).sum(dim=-2)
