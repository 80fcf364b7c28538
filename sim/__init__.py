"""The worlds and the experiments. Depends on `agents`, never on `server`."""
