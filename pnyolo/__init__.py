"""pnyolo: see README.md."""
