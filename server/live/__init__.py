"""Live updates: event streams and the round watcher."""
