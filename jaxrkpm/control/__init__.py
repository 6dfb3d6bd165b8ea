"""Control (layer 5): Jacobian path tracking (thesis Algorithm 3) and the batching of many
problems. Imports the layers below.
"""
