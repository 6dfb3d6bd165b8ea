"""Output (layer 5): solutions as VTU/PVD through meshio, and figures. Imports the layers below
the control layer.
"""
