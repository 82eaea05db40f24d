"""A full-rank Gaussian guide in coordinates whitened by the Laplace approximation.

With the Laplace Gaussian N(m, L L^T) at the MAP, the guide is z = m + L w, w ~ N(a, S S^T),
started at a = 0, S = I (the Laplace Gaussian itself). Adam's steps are of the order of the
learning rate in each coordinate: in w they are fractions of a posterior standard deviation,
whatever the posterior's scale, where on z a posterior narrower than the learning rate (a
horizon known to 0.3 %) is swamped by the optimiser's own jitter.
"""

import torch
from pyro.distributions import MultivariateNormal
from pyro.distributions.transforms import LowerCholeskyAffine
from pyro.infer.autoguide import AutoMultivariateNormal
from pyro.nn import PyroParam


class AutoWhitenedMVN(AutoMultivariateNormal):
    """``AutoMultivariateNormal`` on w = L^-1 (z - m); ``space`` (``Unconstrained``) and
    ``gaussian`` (``laplace.Gaussian`` on that space) give m and L."""

    def __init__(self, model, init_loc_fn, space, gaussian):
        super().__init__(model, init_loc_fn=init_loc_fn, init_scale=1.0)
        self._space, self._gaussian = space, gaussian

    def _setup_prototype(self, *args, **kwargs):
        super()._setup_prototype(*args, **kwargs)
        order = self._order()
        self.mode = self._gaussian.mean.detach()[order]
        self.chol = torch.linalg.cholesky(self._gaussian.covariance[order][:, order])
        self.loc = PyroParam(torch.zeros_like(self.mode))

    def _order(self) -> torch.Tensor:
        """Indices of the space's flat coordinates in the guide's site order."""
        offsets, start = {}, 0
        for k in self._space.names:
            size = self._space.shapes[k].numel()
            offsets[k] = torch.arange(start, start + size)
            start += size
        if set(offsets) != set(self._unconstrained_shapes):
            raise ValueError(f"the Laplace start has sites {sorted(offsets)}, the guide "
                             f"{sorted(self._unconstrained_shapes)}: fit both to the same model")
        return torch.cat([offsets[k] for k in self._unconstrained_shapes])

    def _affine(self):
        """(loc, scale_tril) on z: m + L a and L S."""
        return self.mode + self.chol @ self.loc, self.chol @ (self.scale[..., None] * self.scale_tril)

    def get_posterior(self, *args, **kwargs):
        loc, tril = self._affine()
        return MultivariateNormal(loc, scale_tril=tril)

    def get_transform(self, *args, **kwargs):
        return LowerCholeskyAffine(*self._affine())

    def _loc_scale(self, *args, **kwargs):
        loc, tril = self._affine()
        return loc, tril.pow(2).sum(-1).sqrt()
