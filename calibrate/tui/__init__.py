"""Terminal UI (textual) for the bench: ``bubble tui [--sim]``.

The UI drives the same commissioning flow as ``bubble commission``
(``calibrate.commissioning.run_commissioning``) in a child process and shows the events it emits
(``calibrate.commission_events``). Modules: ``app`` (the application and its key bindings), ``flow_runner`` (the child process),
``inbox`` (thread-safe, coalescing hand-off of flow events to the UI thread), ``halfblock``
(images rendered with half-block characters), ``widgets`` (the panels), ``bench.tcss`` (styles).
"""
