"""What every fit method is: a frozen dataclass whose fields are its settings and whose ``run``
turns them into draws.

One object is both settings and method, so a settings object is all ``fit`` needs
(``fit(model, data, NUTS(num_samples=300))``), a keyword is checked against the fields of
the method it is meant for, and a new method is one class (``bayespd.infer.fit``). The
fields here are shared by every method; ``fit`` uses them for what all methods share
(input checks, the start, the replay into a DataTree), ``run`` only samples.
"""

from dataclasses import dataclass, fields
from typing import ClassVar, NamedTuple

from bayespd.validate import count

MODES = ("best", "weighted")


class Draws(NamedTuple):
    """What ``run`` returns: ``posterior`` ``{site: (chain, draw, ...)}`` (constrained values),
    ``stats`` (``sample_stats``: arrays ``(chain, draw)`` or a Dataset), the gradient
    evaluations, and extra root attributes of the tree."""

    posterior: dict
    stats: object
    grad_evals: int
    attrs: dict | None = None


@dataclass(frozen=True)
class Method:
    """Settings shared by every method.

    ``num_samples`` draws per chain; ``seed`` fixes everything (the start too);
    ``init_values`` start some sites (the others at the prior median); ``init="map"`` starts
    at the MAP (``map_starts`` searches, ``bayespd.infer.mode``); ``modes="weighted"`` fits
    every mode found (``map_starts`` > 1; ``bayespd.infer.mixture``); ``observed`` names the
    likelihood site; ``dims``, ``coords``, ``scene`` and ``constant_data`` lay out the tree.
    ``predictive``: replay the model at every draw (True: ``log_likelihood``,
    ``posterior_predictive``, deterministic sites), at ``n`` draws evenly spaced along each
    chain (an int: a forward solve per replayed draw is the cost), or not at all (False).
    """

    name: ClassVar[str]  # the key in the registry and the tree's ``method`` attribute
    searches_map: ClassVar[bool] = False  # runs the MAP search whatever ``init`` says
    recorded: ClassVar[tuple] = ("num_samples", "seed", "observed", "init", "init_values",
                                 "map_starts", "modes", "predictive")  # to the tree's ``settings``

    num_samples: int = 500
    seed: int = 0
    init_values: dict | None = None
    init: str = "median"
    map_starts: int = 1
    modes: str = "best"
    progress: bool = True
    observed: str = "y"
    dims: dict | None = None
    coords: dict | None = None
    scene: object = None
    constant_data: dict | None = None
    predictive: bool | int = True

    def __post_init__(self):
        if not isinstance(self.predictive, bool):
            count("predictive", self.predictive, 1, "pass True (every draw), False (none) or the "
                  "number of draws to replay")
        count("num_samples", self.num_samples, 1, "ask for at least one draw per chain")
        count("map_starts", self.map_starts, 1, "the MAP search needs at least one start")
        count("seed", self.seed, 0)
        if self.init not in ("median", "map"):
            raise ValueError(f"init must be 'median' or 'map', not {self.init!r}")
        if self.map_starts != 1 and self.init != "map" and not self.searches_map:
            raise ValueError("map_starts searches for the MAP to start from: pass init='map' too")
        if self.modes not in MODES:
            raise ValueError(f"modes must be one of {MODES}, not {self.modes!r}")
        if self.modes == "weighted" and (self.map_starts < 2 or (self.init != "map" and not self.searches_map)):
            raise ValueError("modes='weighted' fits every mode that several MAP searches find: use it "
                             "with map_starts >= 2 (e.g. 8) and, for NUTS, HMC and SVI, init='map'")

    @classmethod
    def settings(cls) -> tuple[str, ...]:
        """The names of the settings (the dataclass fields)."""
        return tuple(f.name for f in fields(cls))

    def record(self) -> dict:
        """The settings that shape the draws, as JSON values (``init_values``: their names)."""
        return {k: sorted(self.init_values or {}) if k == "init_values" else getattr(self, k)
                for k in self.recorded}

    def run(self, model, data: dict, init, search) -> Draws:
        """Draws from the posterior of ``model(**data)`` started by the Pyro init strategy
        ``init``; ``search`` (``bayespd.infer.search.Search``) runs the MAP searches and keeps
        the modes they found."""
        raise NotImplementedError
