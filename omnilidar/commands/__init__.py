"""One module per ``omnilidar`` subcommand (see ``omnilidar.cli``)."""
