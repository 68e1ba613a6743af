"""Analysis of controllers and loops: stability margins of linear predictors (more to come: robustness maps)."""
