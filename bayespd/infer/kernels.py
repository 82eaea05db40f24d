"""Pyro HMC / NUTS kernels that record per-draw statistics and count gradient evaluations."""

import math
from collections import defaultdict

from pyro.infer import HMC, NUTS


class _Recording:
    """After warmup, every ``sample`` appends to ``self.stats``: ``lp`` (minus the potential
    energy, i.e. the log joint density on the unconstrained space, log-Jacobians included),
    ``energy`` (Hamiltonian at the start of the trajectory), ``step_size``, ``n_steps``
    (leapfrog steps), ``diverging`` and ``acceptance_rate`` (mean Metropolis acceptance
    probability over the trajectory, the quantity step-size adaptation targets).
    ``seed_covariance`` (unconstrained space, sites in sorted order) starts the inverse mass
    matrix; ``num_grad_evals`` counts potential-energy evaluations, warmup included."""

    def __init__(self, model, seed_covariance=None, **kwargs):
        super().__init__(model, **kwargs)
        self.seed_covariance = seed_covariance
        self.stats = defaultdict(list)
        self.num_grad_evals = 0

    def _initialize_model_properties(self, model_args, model_kwargs):
        super()._initialize_model_properties(model_args, model_kwargs)
        potential_fn = self.potential_fn

        def counted(z):
            self.num_grad_evals += 1
            self._last_potential = potential_fn(z)
            return self._last_potential

        self.potential_fn = counted

    def _initialize_adapter(self):
        """Seed the inverse mass matrix, then find a step size for it; adaptation goes on."""
        super()._initialize_adapter()
        if self.seed_covariance is not None:
            names = tuple(sorted(self.initial_params))
            self.mass_matrix_adapter.inverse_mass_matrix = {names: self.seed_covariance}
            self._adapter.reset_step_size_adaptation(self._initial_params)

    def _sample_r(self, name):
        r, r_unscaled = super()._sample_r(name)
        self._energy = float(self._kinetic_energy(r_unscaled) + self._potential_energy_last)
        return r, r_unscaled

    def sample(self, params):
        divergences = len(self._divergences)
        self._start_step()
        z = super().sample(params)
        if self._t > self._warmup_steps:
            s = self.stats
            s["lp"].append(-float(self._potential_energy_last))
            s["energy"].append(self._energy)
            s["step_size"].append(float(self.step_size))
            s["diverging"].append(len(self._divergences) > divergences)
            for k, v in self._step_stats().items():
                s[k].append(v)
        return z


class RecordingNUTS(_Recording, NUTS):
    """NUTS; also records ``tree_depth`` (trajectory doublings: at most ``2**tree_depth - 1``
    leapfrog steps)."""

    def _start_step(self):
        self._depth, self._n_steps, self._sum_accept = 0, 0, 0.0

    def _build_tree(self, z, r, z_grads, log_slice, direction, tree_depth, energy_current):
        self._depth = max(self._depth, tree_depth + 1)
        return super()._build_tree(z, r, z_grads, log_slice, direction, tree_depth, energy_current)

    def _build_basetree(self, *args):
        tree = super()._build_basetree(*args)
        self._n_steps += 1
        self._sum_accept += float(tree.sum_accept_probs)
        return tree

    def _step_stats(self):
        return {"tree_depth": self._depth, "n_steps": self._n_steps,
                "acceptance_rate": self._sum_accept / max(self._n_steps, 1)}


class RecordingHMC(_Recording, HMC):
    """Static HMC; the acceptance rate is min(1, exp(-(H_proposal - H_start)))."""

    def _start_step(self):
        self._kinetic = None

    def _kinetic_energy(self, r_unscaled):
        self._kinetic = super()._kinetic_energy(r_unscaled)
        return self._kinetic

    def _step_stats(self):
        proposal = float(self._kinetic.detach() + self._last_potential.detach())  # at the proposal
        delta = proposal - self._energy
        accept = 0.0 if math.isnan(delta) else math.exp(-max(delta, 0.0))
        return {"n_steps": self.num_steps, "acceptance_rate": accept}


KERNELS = {"nuts": RecordingNUTS, "hmc": RecordingHMC}
