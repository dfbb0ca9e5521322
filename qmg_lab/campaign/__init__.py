"""Running a campaign: the plan, the runner that sequences it, the recovery policy, loop design, tuning."""
