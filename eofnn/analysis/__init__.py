"""Analysis of controllers and loops: stability margins of linear predictors, replay of predictors on recorded
telemetry against what it shows was needed."""
