"""Which hand is a session's final one: ``refine_grasp``'s when that stage ran, else
``fit_hand``'s (moved into the object at the first steady frame). The stages after both
(propagate_poses, qa_metrics, pictures) and the catalog rows all take it from here.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from graspcap.tasks.core.geometry import inv_T, transform_points
from graspcap.tasks.hand.fit_hand import HandFit
from graspcap.tasks.hand.refine_grasp import GraspRefinement


class FinalHand(NamedTuple):
    """The final hand's surface and joints.

    vertices_o : (k, 3) float, the surface in the object frame; faces : (f, 3) int.
    joints_w : (21, 3) float, joints in the world; joints_o : (21, 3) the same in the object
    frame.
    """

    vertices_o: np.ndarray
    faces: np.ndarray
    joints_w: np.ndarray
    joints_o: np.ndarray

    @property
    def mesh_o(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices_o, faces)."""
        return self.vertices_o, self.faces


def final_pose(fit: HandFit, refined: GraspRefinement | None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The final hand pose from the results of ``fit_hand`` and ``refine_grasp`` (None when it
    did not run): palm ``T_w_p`` (4, 4), ``angles_rad`` (20,) and joints (21, 3) in the world;
    the refinement's when there is one, else the fit's."""
    if refined is not None:
        return refined.T_w_p, refined.angles_rad, refined.joints_w
    return fit.T_w_p, fit.angles_rad, fit.joints_fit_w


def final_hand(fit: HandFit, refined: GraspRefinement | None, T_w_o: np.ndarray) -> FinalHand:
    """The final hand: the refinement's when ``refined`` is not None, else the fit's, moved
    into the object by ``T_w_o`` (4, 4), the object's pose at the first steady frame
    (``estimate_adjustment``'s ``T_w_o``; unused for a refined hand, which is in the object
    frame already)."""
    if refined is not None:
        return FinalHand(refined.hand_vertices_o, refined.hand_faces, refined.joints_w,
                         refined.joints_o)
    hand = fit.mesh()
    T_o_w = inv_T(T_w_o)
    return FinalHand(transform_points(T_o_w, hand.vertices), hand.faces, fit.joints_fit_w,
                     transform_points(T_o_w, fit.joints_fit_w))
