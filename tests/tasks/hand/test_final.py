"""hand.final: refine_grasp's hand is the final one when it ran, else fit_hand's, moved into the
object at the first steady frame."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from graspcap.tasks.core.geometry import make_T
from graspcap.tasks.hand.final import final_hand, final_pose

RNG = np.random.default_rng(5)
T_W_O = make_T(np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), np.array([0.1, 0.2, 0.5]))
FACES = np.array([[0, 1, 2], [1, 2, 3]])
FIT = SimpleNamespace(
    T_w_p=make_T(np.eye(3), np.array([0.0, 0.0, 0.4])), angles_rad=RNG.normal(size=20),
    joints_fit_w=RNG.normal(size=(21, 3)),
    mesh=lambda: SimpleNamespace(vertices=np.array([[0.1, 0.2, 0.5], [0.1, 0.3, 0.5],
                                                    [0.0, 0.2, 0.5], [0.1, 0.2, 0.6]]),
                                 faces=FACES))
REFINED = SimpleNamespace(
    T_w_p=np.eye(4), angles_rad=np.zeros(20), joints_w=RNG.normal(size=(21, 3)),
    joints_o=RNG.normal(size=(21, 3)), hand_vertices_o=RNG.normal(size=(4, 3)),
    hand_faces=FACES[::-1])


def test_the_refinement_wins_when_there_is_one():
    T_w_p, angles, joints_w = final_pose(FIT, REFINED)
    assert T_w_p is REFINED.T_w_p and angles is REFINED.angles_rad
    assert joints_w is REFINED.joints_w
    hand = final_hand(FIT, REFINED, T_W_O)
    assert hand.vertices_o is REFINED.hand_vertices_o and hand.faces is REFINED.hand_faces
    assert hand.joints_w is REFINED.joints_w and hand.joints_o is REFINED.joints_o
    assert hand.mesh_o == (REFINED.hand_vertices_o, REFINED.hand_faces)


def test_else_the_fit_moved_into_the_object():
    T_w_p, angles, joints_w = final_pose(FIT, None)
    assert T_w_p is FIT.T_w_p and angles is FIT.angles_rad and joints_w is FIT.joints_fit_w
    hand = final_hand(FIT, None, T_W_O)
    # the object frame: x_o = R^T (x_w - t); (0.1, 0.2, 0.5) is the object's origin
    np.testing.assert_allclose(hand.vertices_o, [[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0],
                                                 [0, 0, 0.1]], atol=1e-12)
    assert hand.faces is FACES and hand.joints_w is FIT.joints_fit_w
    back = hand.joints_o @ T_W_O[:3, :3].T + T_W_O[:3, 3]
    np.testing.assert_allclose(back, FIT.joints_fit_w, atol=1e-12)
