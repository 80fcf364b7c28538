"""The web view: its static files and the routes that serve them (and the API docs)."""
