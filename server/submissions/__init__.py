"""POST /submit: quotas, the writer, the service."""
