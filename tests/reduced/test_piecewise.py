"""Piecewise Chebyshev interpolation: exact on polynomials of its degree, spectral on smooth
functions, continuous across breakpoints, differentiable in torch."""
import math

import numpy as np
import pytest
import torch

from bayespd.reduced.piecewise import Piecewise, chebyshev_points


def fitted(f, breaks, n=6):
    return Piecewise(breaks, [np.stack([f(a + (b - a) * s) for s in chebyshev_points(n)])
                              for a, b in zip(breaks[:-1], breaks[1:])])


def test_degree_five_polynomials_are_reproduced():
    f = lambda x: np.array([x**5 - 2 * x**2 + 1.0, 3 * x**4])  # noqa: E731
    p = fitted(f, [0.0, 0.3, 1.0, 2.5])
    for x in np.linspace(0, 2.5, 37):
        np.testing.assert_allclose(p(x).numpy(), f(x), rtol=1e-11, atol=1e-11)


def test_error_falls_spectrally_with_pieces():
    """exp on k pieces: the degree-5 interpolation error scales as (1/k)^6."""
    xs = np.linspace(0.0, 1.0, 101)
    errors = [max(abs(float(fitted(np.exp, np.linspace(0, 1, k + 1))(x)) - math.exp(x)) for x in xs)
              for k in (1, 2, 4)]
    assert errors[0] < 1e-5
    for coarse, fine in zip(errors[:-1], errors[1:]):
        assert 2 ** 5 < coarse / fine < 2 ** 7


def test_continuous_and_differentiable():
    p = fitted(np.sin, [0.0, 1.0, 2.0])
    left, right = p(torch.tensor(1.0 - 1e-13)), p(torch.tensor(1.0))
    assert abs(float(left - right)) < 1e-12
    x = torch.tensor(0.7, requires_grad=True)
    (g,) = torch.autograd.grad(p(x), x, create_graph=True)
    (g2,) = torch.autograd.grad(g, x)
    assert abs(float(g.detach()) - math.cos(0.7)) < 1e-4 and abs(float(g2) + math.sin(0.7)) < 1e-2


def test_outside_the_range_is_refused():
    with pytest.raises(ValueError, match=r"outside the range \[0, 2\].*rebuild"):
        fitted(np.sin, [0.0, 1.0, 2.0])(2.1)
