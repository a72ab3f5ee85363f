"""The 20-DoF hand model (mesh, IK, surface distances) and the stages that fit it: fit_hand,
refine_grasp.
"""
