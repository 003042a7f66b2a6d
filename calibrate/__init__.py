"""Commissioning: the flow, acceptance checks, pose check, reports, sensor registry, TUI, command line."""
