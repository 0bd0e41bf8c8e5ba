"""analysis: see README.md (work in progress, tracked by its issue)."""
