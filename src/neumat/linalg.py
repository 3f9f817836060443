"""Linear algebra whose result must not depend on how many cores a job was given."""

from threadpoolctl import threadpool_limits


def one_blas_thread():
    """A context with one BLAS/LAPACK thread for numpy. OpenBLAS splits a long product (a Gram
    matrix over 10^5 bins) differently for each thread count, so its last bits changed with the
    job's threads, i.e. with `snakemake --cores`, and AugMERL's PCA and every fit after it with
    them (figures: README, known limits). The products this guards run once per run."""
    return threadpool_limits(1, user_api="blas")
