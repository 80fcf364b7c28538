"""The HTTP surface: routes, schemas, dependencies, errors, limits."""
