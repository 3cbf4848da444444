"""Fault injection shared by the robustness tests (not a test module)."""

import contextlib
import resource
import signal


def raise_once(original, exception, *, call_through=False, armed=True):
    """(replacement, state): a stand-in for `original` that, while ``state["armed"]``, raises
    `exception` at its next call (after running the original when `call_through`) and disarms;
    otherwise it behaves as the original. `armed`: the initial state."""
    state = {"armed": armed}

    def replacement(*args, **kwargs):
        if state["armed"]:
            state["armed"] = False
            if call_through:
                original(*args, **kwargs)
            raise exception
        return original(*args, **kwargs)

    return replacement, state


@contextlib.contextmanager
def signal_handler(sig, handler):
    """`handler` installed for `sig` inside the block, the previous one restored after. A test
    that sends itself a signal sets the disposition it assumes: a process started in the
    background by a non-interactive shell (`cmd &`) inherits SIGINT ignored."""
    before = signal.signal(sig, handler)
    try:
        yield
    finally:
        signal.signal(sig, before)


@contextlib.contextmanager
def file_size_limit(limit: int):
    """Files can grow to `limit` bytes at most (RLIMIT_FSIZE): a write beyond fails with EFBIG
    (Python ignores SIGXFSZ), as a full disk fails it. Restored on exit."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
