"""``moved_share``: how much of an object's surface a motion moves visibly off itself, the test
that tells an object's own symmetry (other views see it alike) from a near-symmetry (another
view may show the handle, the nozzle, the spout)."""

from __future__ import annotations

import numpy as np
import pytest

from graspcap.synth.objects import procedural_object
from graspcap.tasks.object_pose.estimate_adjustment import PRESETS
from graspcap.tasks.object_pose.registration.engine import RegistrationConfig, prepare_model
from graspcap.tasks.object_pose.registration.symmetry import about_axis, moved_share

CONFIG = PRESETS["default"]


def _share(model, T_o_o):
    return moved_share(model, T_o_o, CONFIG.symmetric_tie_moved_m)


@pytest.mark.parametrize("kind", ["can", "glass", "bulb"])
def test_a_turn_about_an_axis_of_revolution_is_a_tie(kind):
    obj = procedural_object(kind)
    model = prepare_model(obj.vertices, obj.faces, RegistrationConfig())
    assert _share(model, np.eye(4)) == 0.0
    # its axis: the principal axis about which a turn moves least (a glass's chip or a can's
    # tab breaks revolution_axis's every-sample test)
    axis = min(model.axes.T, key=lambda a: _share(model, about_axis(model, a, np.radians(60))))
    for angle in (60.0, 180.0):
        turned = about_axis(model, axis, np.radians(angle))
        assert _share(model, turned) <= CONFIG.symmetric_tie_share


@pytest.mark.parametrize("kind", ["mug", "spray_bottle", "carton", "bottle"])
def test_a_near_symmetric_objects_half_turns_are_not(kind):
    obj = procedural_object(kind)
    model = prepare_model(obj.vertices, obj.faces, RegistrationConfig())
    shares = [_share(model, about_axis(model, a, np.pi)) for a in model.axes.T]
    assert min(shares) > CONFIG.symmetric_tie_share, shares  # a handle, nozzle, spout, cap
