"""What every domain of the server stands on: its settings, database, tables, authentication,
logs, metrics, errors, checksums and the lab's credentials; it imports no domain."""
