"""Offline analysis of recorded telemetry: replaying predictors against what the telemetry shows was needed."""
