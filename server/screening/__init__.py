"""The screener pool: verdicts in a process that never touches the database."""
