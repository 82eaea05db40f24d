"""bp.Held: the held values reach predict and the per-draw diagnostics; the rest are the
parameters; a held name the scene does not have is refused."""
import numpy as np
import pytest
import torch

import bayespd as bp
from tests.conftest import plate_scene as plate


def test_held_delta_gives_the_full_scenes_prediction_and_leaves_the_moduli():
    scene = plate()
    held = bp.Held(scene, delta=2.2)
    assert held.param_names == ("K", "G")
    u = held.predict({"K": 3.0, "G": 1.5})
    assert torch.equal(u, scene.predict({"K": 3.0, "G": 1.5, "delta": 2.2}))


def test_diagnostics_see_the_held_value_at_every_draw():
    class Recorder:
        param_names, material = ("K", "G", "delta"), None
        particles = observation = None

        def diagnostics(self, draws):
            return {"delta": draws["delta"]}

    out = bp.Held(Recorder(), delta=3.0).diagnostics({"K": np.ones((2, 5)), "G": np.ones((2, 5))})
    assert out["delta"].shape == (2, 5) and np.all(out["delta"] == 3.0)
    assert bp.Held(plate(), delta=2.2).diagnostics({"K": np.ones(3), "G": np.ones(3)}) == {}


def test_holding_an_unknown_parameter_or_none_is_refused():
    with pytest.raises(ValueError, match=r"cannot hold \['nu'\]"):
        bp.Held(plate(), nu=0.3)
    with pytest.raises(ValueError, match="name at least one"):
        bp.Held(plate())
