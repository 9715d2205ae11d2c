"""The task: the course and its on-board tracker, and the judge (reward terms and termination reasons)."""
