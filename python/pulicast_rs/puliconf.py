"""puliconf's `Setting`, as Pulicast 2.x programs declare settings, on the
owned settings of pulicast-rs (so the 2.x tools, `puli config` and
`FleetSettings` read and change them alike).

A 2.x program changes its import line
`from pulicast_tools.puliconf.setting import Setting, accept_range` to
`from pulicast_rs.puliconf import Setting, accept_range`:

    node = pulicast.ThreadedNode("rover", default_namespace="/rover1")
    gain = Setting("gain", node, 0.5, validate_roc=accept_range(0, 1),
                   value_changed=lambda: print("gain is now", gain.value))

The setting's channels are puliconf's: `rover1/.config/gain` and
`rover1/.config/gain.r`. What differs from 2.x is in docs/python.md
("What differs from the 2.x package").
"""

import math
import threading
import warnings
from typing import Any, Callable, Generic, Optional, Tuple, TypeVar

T = TypeVar("T")

ValidationFunction = Callable[[Optional[T]], Tuple[str, bool]]

_TYPES = (bool, int, float, str)


def accept_everything() -> ValidationFunction:
    """Accepts every value (and no value: a tool may unset it)."""

    def accept(value):
        return "", True

    accept._pulicast_accepts_all = True
    return accept


def accept_nothing() -> ValidationFunction:
    """Accepts no request: the setting is read-only."""

    def refuse(value):
        return "static value is read-only", False

    refuse._pulicast_read_only = True
    return refuse


def accept_only(*acceptable_values) -> ValidationFunction:
    """Accepts the values given."""
    acceptable = set(acceptable_values)

    def accept_if_in_values(roc):
        if roc is not None and roc in acceptable:
            return "", True
        return f"must be in {acceptable}", False

    return accept_if_in_values


def accept_at_least(minimum) -> ValidationFunction:
    """Accepts values >= `minimum`."""

    def accept_if_large_enough(roc):
        if roc is not None and minimum <= roc:
            return "", True
        return f"must be at least {minimum}", False

    return accept_if_large_enough


def accept_at_most(maximum) -> ValidationFunction:
    """Accepts values <= `maximum`."""

    def accept_if_small_enough(roc):
        if roc is not None and roc <= maximum:
            return "", True
        return f"must be at most {maximum}", False

    return accept_if_small_enough


def accept_above(v) -> ValidationFunction:
    """Accepts values > `v`."""

    def accept_if_large_enough(roc):
        if roc is not None and v < roc:
            return "", True
        return f"must be above {v}", False

    return accept_if_large_enough


def accept_at_below(v) -> ValidationFunction:
    """Accepts values < `v` (2.x's name)."""

    def accept_if_small_enough(roc):
        if roc is not None and roc < v:
            return "", True
        return f"must be below {v}", False

    return accept_if_small_enough


def accept_range(minimum, maximum) -> ValidationFunction:
    """Accepts values in [minimum, maximum]."""

    def accept_if_in_range(roc):
        if roc is not None and minimum <= roc <= maximum:
            return "", True
        return f"must be in [{minimum}, {maximum}]", False

    return accept_if_in_range


def accept_in_interval(
    min_v=-math.inf, max_v=math.inf, all_above=-math.inf, all_below=math.inf
) -> ValidationFunction:
    """Accepts values v with min_v <= v <= max_v and all_above < v < all_below.

    >>> half_open = accept_in_interval(all_above=5, max_v=7)
    >>> half_open.__doc__, half_open(6)[1], half_open(5)[1], half_open(7)[1]
    ('must be in (5, 7]', True, False, True)
    """
    if not all_above <= all_below:
        raise ValueError(f"all_above must be below all_below, and {all_above} is not below {all_below}")
    if not min_v <= max_v:
        raise ValueError(f"min_v must be at most max_v, and {min_v} is not at most {max_v}")
    left_closed = all_above < min_v
    right_closed = max_v < all_below
    left = f"[{min_v}" if left_closed else f"({all_above}"
    right = f"{max_v}]" if right_closed else f"{all_below})"
    description = f"must be in {left}, {right}"

    def check_in_range(roc):
        inside = roc is not None and all_above < roc < all_below and min_v <= roc <= max_v
        return ("", True) if inside else (description, False)

    check_in_range.__doc__ = description
    return check_in_range


class Setting(Generic[T]):
    """A setting this node owns, as puliconf declares it:
    `Setting(name, namespace, initial_value, value_type=None,
    value_changed=lambda: None, validate_roc=accept_everything())`.

    `namespace` is a node or a namespace of it (`node / "arm"`). Requests
    are checked by `validate_roc(value) -> (warning, accepted)`;
    `value_changed()` is called after each change. Keep the object: the
    setting is withdrawn when it is dropped.
    """

    def __init__(
        self,
        name: str,
        namespace,
        initial_value=None,
        value_type=None,
        value_changed: Callable[[], None] = lambda: None,
        validate_roc: ValidationFunction = accept_everything(),
    ):
        if initial_value is not None and value_type is not None:
            if type(initial_value) == value_type:  # noqa: E721 (2.x compares types exactly)
                warnings.warn(
                    f"Initial value and value type of {name} were both specified. "
                    "This is redundant and therefore should be avoided."
                )
            else:
                raise ValueError(
                    f"Specified type {value_type} for {name} while its initial value "
                    f"{initial_value} is of type {type(initial_value)}!"
                )
        if initial_value is None and value_type is None:
            raise ValueError("You either need to pass an initial value or a value type to a setting!")
        if value_type is None:
            value_type = type(initial_value)
        if value_type not in _TYPES:
            raise TypeError(
                f"pulicast_rs settings hold a bool, int, float or str, not {value_type.__name__} "
                "(ZCM classes as settings are not supported)"
            )
        if initial_value is None:
            # pulicast-rs settings start with a value: the type's own.
            initial_value = value_type()
        native_node = getattr(getattr(namespace, "_node", None), "_native", None)
        if native_node is None:
            raise TypeError(f"namespace must be a pulicast_rs ThreadedNode or a namespace of one, not {namespace!r}")
        # 2.x never checks the initial value (only a reset to it): neither
        # does this, while the setting is made.
        made = threading.Event()

        def check(value):
            if not made.is_set() and value == initial_value and type(value) is type(initial_value):
                return None
            warning, accepted = validate_roc(value)
            return None if accepted else (warning or "refused")

        read_only = getattr(validate_roc, "_pulicast_read_only", False)
        # Checked natively when it can be: read-only, or anything.
        plain = read_only or getattr(validate_roc, "_pulicast_accepts_all", False)
        # What a poke is answered with: the validator's words for no value.
        try:
            about = "" if plain else validate_roc(None)[0]
        except Exception:  # a validator that can't take None says nothing
            about = ""
        native_ns = native_node.ns("/" + str(namespace._path).strip("/"))
        self._setting = native_ns.setting(
            name,
            initial_value,
            read_only=read_only,
            check=None if plain else check,
            description=about,
        )
        made.set()
        # Not through `self`: the node would hold the setting's object, and
        # the setting would never be withdrawn when the program drops it.
        self._setting.on_change(lambda _value: value_changed())

    @property
    def value(self) -> Optional[T]:
        """The value; `None` once a tool unset it."""
        return self._setting.value

    @property
    def name(self) -> str:
        """The fleet-wide name (`rover1/gain`)."""
        return self._setting.name

    def get(self, default: Optional[T] = None) -> Any:
        """The value, or `default` if it is unset."""
        value = self._setting.value
        return default if value is None else value
