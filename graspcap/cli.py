"""Command-line front end: `graspcap synth|validate|demo|...` (filled in per command)."""

def main(argv=None):
    raise SystemExit("not yet")
