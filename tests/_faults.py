"""Fault injection shared by the streaming robustness tests (not a test module)."""


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
