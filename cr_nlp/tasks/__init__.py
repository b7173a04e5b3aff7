"""The tasks, each one problem definition (objective, constraints, result): IK first."""
