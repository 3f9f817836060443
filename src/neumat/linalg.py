"""Linear algebra whose result must not depend on how many cores a job was given."""

from threadpoolctl import threadpool_limits


def one_blas_thread():
    """A context with one BLAS/LAPACK thread for numpy. OpenBLAS splits a long product (a Gram
    matrix over 10^5 bins) differently for each thread count, so its last bits changed with the
    job's threads, i.e. with `snakemake --cores`: on the realistic default config, AugMERL's PCA
    coefficients moved by up to 0.02 between a 1- and a 2-core run, and most NeuMERL fits then
    differed. The products this guards are done once per run (seconds)."""
    return threadpool_limits(1, user_api="blas")
