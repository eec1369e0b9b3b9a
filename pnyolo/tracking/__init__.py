"""Tracks over the frames of a sequence: a ground-plane tracker and its scoring with motmetrics."""
