"""What every layer may use: the outcome enumerations, the option validators, BLAS/LAPACK
threads, the release of compiled programs, and the progress bars of long calls. Imports
nothing of jaxrkpm.
"""
