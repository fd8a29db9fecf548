"""Jobs that chain the others: the demo at toy scale, and a recipe's reproduction from nothing (record,
train, calibrate, experiments, comparison). Each resumes where an interrupted run stopped."""
