"""Priors for bounded physical parameters."""

import torch
import pyro.distributions as dist
from pyro.distributions import constraints
from torch.distributions.transforms import AffineTransform
from torch.distributions.utils import broadcast_all


class ScaledBeta(dist.TransformedDistribution):
    """``low + (high - low) * Beta(concentration1, concentration0)``.

    Unlike a plain transformed Beta, its ``support`` is ``interval(low, high)``, so NUTS and
    the autoguides map it to the real line through ``biject_to(interval)`` and never propose
    values outside ``[low, high]``. The default (2, 2) puts zero density at both ends: the
    default prior for a bounded length such as the peridynamic horizon.
    """

    arg_constraints = {
        "concentration1": constraints.positive,
        "concentration0": constraints.positive,
    }

    def __init__(self, low, high, concentration1=2.0, concentration0=2.0, validate_args=None):
        self.low, self.high, c1, c0 = broadcast_all(low, high, concentration1, concentration0)
        if not torch.all(self.high > self.low):
            raise ValueError("ScaledBeta needs high > low")
        base = dist.Beta(c1, c0, validate_args=validate_args)
        super().__init__(
            base, AffineTransform(self.low, self.high - self.low), validate_args=validate_args
        )

    @property
    def concentration1(self):
        return self.base_dist.concentration1

    @property
    def concentration0(self):
        return self.base_dist.concentration0

    @constraints.dependent_property(is_discrete=False, event_dim=0)
    def support(self):
        return constraints.interval(self.low, self.high)

    @property
    def mean(self):
        return self.low + (self.high - self.low) * self.base_dist.mean

    @property
    def variance(self):
        return (self.high - self.low) ** 2 * self.base_dist.variance

    def expand(self, batch_shape, _instance=None):
        shape = torch.Size(batch_shape)
        return ScaledBeta(
            self.low.expand(shape),
            self.high.expand(shape),
            self.concentration1.expand(shape),
            self.concentration0.expand(shape),
            validate_args=self._validate_args,
        )
