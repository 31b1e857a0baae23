"""imaging stage of the breast-modelling toolkit."""
