"""Artist tools beside the deformation: bake (PC2 or shape keys), painted weights and the weight preview."""
