"""The database: tables, CRUD statements, migrations, engines and sessions."""
