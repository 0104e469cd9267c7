"""Click commands: each builds a config, calls one library function and reports."""
