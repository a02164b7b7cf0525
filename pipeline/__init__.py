"""The pipeline: games, environments, rollout, executors, jobs and the command line."""
