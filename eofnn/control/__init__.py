"""Loop-side controllers (the lead is moving baselines and predictive controllers here); adaptive filters."""
