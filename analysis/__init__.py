"""plenodust analysis package."""
