"""The detect_keypoints stage and its image detector (MediaPipe Hands)."""
