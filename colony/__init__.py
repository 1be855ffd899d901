"""The `colony` command line: one entry point for every process role and lab script."""
