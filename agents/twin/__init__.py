"""so101-twin agents."""
