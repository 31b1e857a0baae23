"""meshing stage of the breast-modelling toolkit."""
