"""plenodust service package."""
