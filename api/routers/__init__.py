"""One router per resource: rig, takes, calibrations, jobs."""
