"""The static hand by structure from motion (the paper's stage 2): select_steady,
reconstruct_hand and its solver pieces, crosscheck_sfm.
"""
