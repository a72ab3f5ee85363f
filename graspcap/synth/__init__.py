"""Synthetic capture rig: sessions written to the contract, with ground truth."""
