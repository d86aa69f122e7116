"""Messages, key expressions, configuration types and the bus layer shared by every cvvc-edge process."""
