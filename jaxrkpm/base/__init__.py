"""What every layer may use: the outcome enumerations, BLAS/LAPACK threads, and the release
of compiled programs. Imports nothing of jaxrkpm.
"""
