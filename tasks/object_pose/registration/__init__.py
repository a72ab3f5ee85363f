"""The registration engine the object-pose stages share: point clouds, RANSAC, ICP, symmetry
probes, free rotation, depth agreement, Open3D thread control.
"""
