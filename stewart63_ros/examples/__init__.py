"""Examples for users of the package (a control law of one's own)."""
