"""The surgeon in the loop: LeRobot teleoperators mapped to the needle holder, who is in control, the
recorded run (interventions as data) and its live view. ``docs/surgeon.md`` describes it."""
