"""Learning side: session data loading, depth networks, loss, metrics, training, export, inference."""
