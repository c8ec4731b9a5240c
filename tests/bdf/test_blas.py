import threading

from threadpoolctl import threadpool_info, threadpool_limits

from bdf import _blas


def blas_threads() -> set[int]:
    return {lib["num_threads"] for lib in threadpool_info() if lib["prefix"] == "libscipy_openblas"}


def test_small_work_runs_on_one_blas_thread_and_the_count_comes_back():
    with threadpool_limits(limits=2, user_api="blas"):
        assert blas_threads() == {2}
        with _blas.one_thread():
            assert blas_threads() == {1}
        assert blas_threads() == {2}


def test_a_worker_thread_limits_and_restores_the_count():
    original, seen = blas_threads(), {}

    def work():
        with _blas.one_thread():
            seen["inside"] = blas_threads()
        seen["after"] = blas_threads()

    worker = threading.Thread(target=work)
    worker.start()
    worker.join(10)
    assert seen == {"inside": {1}, "after": original}
    with _blas.one_thread():  # the worker gave up control: this thread can limit now
        assert blas_threads() == {1}
    assert blas_threads() == original


def test_tasks_in_threads_run_side_by_side_on_one_blas_thread_each_and_answer_in_order():
    both = threading.Barrier(2, timeout=10)  # the first two meet: they run side by side

    def task(k):
        if k < 2:
            both.wait()
        return k, blas_threads()

    with threadpool_limits(limits=2, user_api="blas"):
        answers = _blas.in_threads([lambda k=k: task(k) for k in range(6)])
        assert [k for k, _ in answers] == list(range(6))
        assert all(threads == {1} for _, threads in answers)
        assert blas_threads() == {2}
