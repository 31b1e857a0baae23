"""registration stage of the breast-modelling toolkit."""
