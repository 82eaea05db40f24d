"""Bonds: the partial-volume ramps in delta."""
import pytest
import torch

import bayespd as bp


def test_smooth_partial_volume_is_c1_in_delta():
    """The smoothstep ramp has the linear one's values at the ends and mid-point (0, 1/2, 1)
    and the same mean 1/2 over the ramp; its derivative in delta is continuous (0 at both
    ends, where the linear ramp's jumps by 1/h); an unknown rule is refused."""
    from bayespd.bonds import partial_volume

    h, length = 0.5, torch.tensor(1.3)
    ends = torch.tensor([length - h / 2, length + h / 2], dtype=torch.float64)
    for rule, jump in (("linear", 1 / h), ("smooth", 0.0)):
        slopes = []
        for side in (-1e-9, 1e-9):
            d = (ends + side).requires_grad_()
            slopes.append(torch.autograd.grad(partial_volume(length, d, h, rule).sum(), d)[0])
        assert torch.allclose((slopes[1] - slopes[0]).abs(), torch.tensor([jump, jump], dtype=torch.float64), atol=1e-6)
    t = torch.linspace(0, 1, 10001, dtype=torch.float64)
    w = partial_volume(length, length - h / 2 + t * h, h, "smooth")
    assert float(w[0]) == 0.0 and float(w[-1]) == 1.0 and float(w[5000]) == pytest.approx(0.5, abs=1e-12)
    assert float(torch.trapezoid(w, t)) == pytest.approx(0.5, abs=1e-8)
    with pytest.raises(ValueError, match="partial-volume rule"):
        bp.find_bonds(bp.grid_2d(4.0, 4.0, 1.0), 2.0, rule="cubic")
