"""Tables and figures of the workflow's results."""
