"""One module per ``fastgha`` subcommand (see ``fastgha_core.cli``)."""
