"""What a session hands on: propagate_poses, qa_metrics and its measures, the QA pictures."""
