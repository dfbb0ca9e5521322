"""Reading run files back: the analysis, characterization procedures, Allan deviation, figures."""
