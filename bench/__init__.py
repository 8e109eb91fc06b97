"""Speed-against-error benchmark, hard-case stability suite and synthetic test frames."""
