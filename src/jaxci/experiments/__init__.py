"""Stage 6 of the flow: experiment configs (the YAML schema and its errors), the runner, its report, results and
plots."""
