"""The stages' one shape (`processing.stage.Stage`): every stage a pipeline may run has it,
and the pipeline drives their lives (tare, gap, estimator, rate, status) without naming one."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from ftsensord.processing.pipeline import STAGE_TYPES
from ftsensord.processing.stage import Stage


@pytest.mark.parametrize("kind", STAGE_TYPES, ids=lambda k: k.__name__)
def test_every_stage_type_has_the_stage_shape(kind):
    for member in ("configure", "gap", "restart", "tared", "status"):
        ours, theirs = inspect.signature(getattr(Stage, member)), inspect.signature(getattr(kind, member))
        assert list(ours.parameters) == list(theirs.parameters), f"{kind.__name__}.{member}{theirs}"
    assert isinstance(kind.name, str) and kind.name


def test_the_stages_names_are_the_status_keys_and_unique():
    names = [k.name for k in STAGE_TYPES]
    assert len(set(names)) == len(names) and names == ["temperature", "stray", "silicone"]


def test_the_temperature_stage_hands_on_the_zero_it_compensated():
    """A tare hands the zero through the stages in the order they act (`STAGE_TYPES`): the
    temperature stage gives the stages after it, and the estimator, the zero brought to its
    reference, as every sample after the tare is."""
    from ftsensord.calibration.thermal import CalibrationTemperature, ThermalLaws
    from ftsensord.processing.temperature import ThermalCompensation

    stage = ThermalCompensation(ThermalLaws(), 2, CalibrationTemperature(25.0, 20.0, 30.0))
    stage.observe([45.0, 45.0])
    zero = np.full(6, 1e-4)
    handed = stage.tared(zero)
    assert np.array_equal(handed, stage.apply(zero)) and not np.allclose(handed, zero)
