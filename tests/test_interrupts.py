"""An interrupt that lands where Python drops exceptions (a weakref callback run by the garbage collector) still
stops the command: the fault that once let a Ctrl-C'd fit run on to its end."""

import subprocess
import sys
import textwrap

import pytest

# The signal is delivered inside a weakref callback: Python runs the handler there, its KeyboardInterrupt
# cannot propagate, and it prints "Exception ignored in ..." and goes on.
DROPPED = textwrap.dedent("""
    import os, signal, sys, time, weakref

    # As an interactive shell starts it: a background job (nohup ... &) inherits SIGINT ignored.
    signal.signal(signal.SIGINT, signal.default_int_handler)

    class Thing:
        pass

    def callback(ref):
        os.kill(os.getpid(), signal.SIGINT)  # the handler runs before this call returns, inside the callback

    def drop_an_interrupt():
        thing = Thing()
        ref = weakref.ref(thing, callback)
        del thing  # the callback runs here

    {body}
""")


def _run(body, timeout=60):
    script = DROPPED.format(body=body)
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=timeout)


def test_without_the_guard_python_drops_the_interrupt():
    """The fault is real: with Python's own handler the interrupt is printed as ignored and the work goes on."""
    out = _run("drop_an_interrupt()\nprint('went on')")
    assert out.returncode == 0 and "went on" in out.stdout
    assert "Exception ignored" in out.stderr and "KeyboardInterrupt" in out.stderr


def test_a_dropped_interrupt_is_raised_at_the_next_safe_point_and_not_reported_as_ignored():
    body = textwrap.dedent("""
        from cpas_bayes.core import interrupts
        with interrupts.catching():
            drop_an_interrupt()
            print('went on to the safe point', interrupts.requested())
            try:
                interrupts.raise_if_requested()
            except KeyboardInterrupt:
                print('raised')
        print('after: requested', interrupts.requested(), 'handler restored',
              signal.getsignal(signal.SIGINT) is signal.default_int_handler)
    """)
    out = _run(body)
    assert out.returncode == 0, out.stderr
    assert "went on to the safe point True" in out.stdout and "raised" in out.stdout
    assert "after: requested False handler restored True" in out.stdout
    assert out.stderr == ""


@pytest.mark.parametrize("start,wait", [("", "ex.map(time.sleep, [30])"),
                                        ("handle = ex.submit(time.sleep, 30)", "handle.result()")],
                         ids=["map", "submit"])
def test_a_process_pool_wait_stops_within_a_second_after_a_dropped_interrupt(start, wait):
    """The executor's wait loops (``map`` and a submitted task's ``result``) are safe points: a 30 s task is
    abandoned, and its worker ended."""
    body = textwrap.dedent(f"""
        from cpas_bayes.core import interrupts
        from cpas_bayes.core.executor import ProcessExecutor
        if __name__ == "__main__":
            with interrupts.catching(), ProcessExecutor(1) as ex:
                ex.map(abs, [1])  # the worker is up
                {start}
                drop_an_interrupt()
                started = time.perf_counter()
                try:
                    {wait}
                except KeyboardInterrupt:
                    print(f'stopped after {{time.perf_counter() - started:.2f}} s')
    """)
    out = _run(body)
    assert out.returncode == 0, out.stderr
    assert "stopped after" in out.stdout, (out.stdout, out.stderr)
    assert float(out.stdout.split("stopped after")[1].split()[0]) < 1.0
    assert "Exception ignored" not in out.stderr
    # the ended worker held numba's start-up lock: no semaphore left for the resource tracker to report
    assert "leaked" not in out.stderr, out.stderr


def test_the_serial_executor_stops_before_the_next_task():
    body = textwrap.dedent("""
        from cpas_bayes.core import interrupts
        from cpas_bayes.core.executor import Executor
        ran = []
        def task(x):
            ran.append(x)
            if x == 1:
                drop_an_interrupt()
        with interrupts.catching():
            try:
                Executor().map(task, [1, 2, 3])
            except KeyboardInterrupt:
                print('ran', ran)
    """)
    out = _run(body)
    assert out.returncode == 0, out.stderr
    assert "ran [1]" in out.stdout


def test_a_signal_the_process_was_started_ignoring_stays_ignored():
    body = textwrap.dedent("""
        from cpas_bayes.core import interrupts
        signal.signal(signal.SIGINT, signal.SIG_IGN)   # a background job of a non-interactive shell
        with interrupts.catching():
            inside = signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGINT)
            print('ignored inside', inside, 'requested', interrupts.requested())
        print('after', signal.getsignal(signal.SIGINT) is signal.SIG_IGN)
    """)
    out = _run(body)
    assert out.returncode == 0, out.stderr
    assert "ignored inside True requested False" in out.stdout and "after True" in out.stdout


def test_submit_runs_in_order_of_need_and_gives_the_same_results_on_every_executor():
    """``submit`` starts a task and returns a handle: on a pool it runs while the caller works; on the serial
    executor it runs when its result is first asked for, after the caller's own work."""
    from cpas_bayes.core.executor import Executor, ProcessExecutor

    order = []

    def task(x):
        order.append(("task", x))
        return x * x

    handle = Executor().submit(task, 3)
    order.append(("caller", None))
    assert handle.result() == 9 and handle.result() == 9
    assert order == [("caller", None), ("task", 3)]      # run once, when asked
    with ProcessExecutor(2) as ex:
        handles = [ex.submit(abs, -v) for v in range(5)]
        assert [h.result() for h in handles] == list(range(5))
