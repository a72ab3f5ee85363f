"""Loading and validating a capture session; its file checks and readers; colour frame reading."""
