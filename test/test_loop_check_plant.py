"""The closed-loop check's plant is a piece (analysis.loop_settings.ModelPlant, or any plant with
tip() and step()): the model as an explicit plant gives the check's own numbers, and a real
finger of sim/plants runs in the same loop."""
import math

from chamber_models import OneChamber, _chamber_facts
import numpy as np
import pytest

from soft_gripper_sdre.analysis import loop_settings as ls
from soft_gripper_sdre.sim.plants.presets import plant_pair


class Finger:
    """A preset's finger as the check's plant: its tip's first d coordinates [m]."""

    def __init__(self, plant, d: int) -> None:
        self.plant, self.d = plant, d
        plant.reset()
        self.rest = self.tip()
        self.farthest = 0.0                     # the largest distance from rest so far [m]

    def tip(self):
        return np.asarray(self.plant.tip(), dtype=float)[:self.d]

    def step(self, u, dt):
        self.plant.step(np.asarray(u, dtype=float).reshape(-1), dt)
        self.farthest = max(self.farthest, float(np.linalg.norm(self.tip() - self.rest)))


class Blows:
    """A plant whose tip stops being finite after a few steps."""

    def __init__(self) -> None:
        self.k = 0

    def tip(self):
        return np.array([0.0, 0.06]) if self.k < 5 else np.array([np.nan, 0.06])

    def step(self, u, dt):
        self.k += 1


@pytest.fixture(scope='module')
def case():
    model, facts = OneChamber(), _chamber_facts(travel=2e-3)
    return model, facts, ls.settings_for(model, facts, 2.0, 1.0)


@pytest.mark.parametrize('gain', [1.0, 0.5])
def test_the_model_as_an_explicit_plant_gives_the_checks_own_numbers(case, gain):
    model, facts, settings = case
    own = ls.check_on_model(model, settings, facts, gain_error=gain)
    explicit = ls.check_on_model(model, settings, facts, plant=ls.ModelPlant(model, gain))
    assert own == explicit
    assert math.isfinite(own.rmse_rel)


def test_a_real_finger_runs_in_the_same_loop_from_its_own_rest(case):
    model, facts, settings = case
    finger = Finger(plant_pair('pneumatic1')[0], 2)
    result = ls.check_on_model(model, settings, facts, plant=finger)
    assert math.isfinite(result.rmse_rel) and not result.diverged
    assert result.outside == 0                 # the law kept the chamber within its bounds
    # the real finger moved under the loop, and its time is the whole check's
    assert 0.3 * facts.travel < finger.farthest < 20 * facts.travel
    steps = round(sum(ls.CHECK_PROFILE.values()) / settings.control_period) + 1
    assert finger.plant.state.t == pytest.approx(steps * settings.control_period)


def test_a_plant_that_stops_being_finite_is_a_diverged_check(case):
    model, facts, settings = case
    result = ls.check_on_model(model, settings, facts, plant=Blows())
    assert result.diverged and result.rmse_rel == math.inf
