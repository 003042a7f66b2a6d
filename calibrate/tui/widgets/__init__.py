"""The panels of the bench TUI; each consumes commissioning events or snapshots and never blocks."""
