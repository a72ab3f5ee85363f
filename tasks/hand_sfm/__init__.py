"""Stage 2, the static hand by structure from motion: select_steady, reconstruct_hand and its
solver pieces, crosscheck_sfm.
"""
