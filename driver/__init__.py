"""plenodust driver package."""
