"""A process exit with a chosen code that needs neither the GIL nor the main thread: `exit_after(seconds, code)`.

Why: tearing rclpy down can spin forever with the GIL held. Fast DDS 2.14 (the PyPI wheels') destroys a
participant with `set_listener(nullptr)`, which waits on a condition variable, until `steady_clock::time_point::max()`,
for the participant's discovery callbacks to end. The wheel's libstdc++ (built for glibc 2.28, without
`pthread_cond_clockwait`) waits on the system clock and converts that deadline by adding max − now to the system
clock's now: it overflows into the past, every wait returns at once, and the loop spins (objdump of the wheel's
`DomainParticipant::set_listener`: `pthread_cond_timedwait` between calls of both clocks' `now`). It holds the
listener's mutex all but an instant of each turn, so a discovery callback that needs the mutex to finish (another
participant leaving at the same moment, as at the end of every team run) starves: the same loop built here from a
clock libstdc++ does not wait on natively kept another thread from a mutex for 9 minutes at 100 % CPU, beside a
test run. (Built where glibc has `pthread_cond_clockwait`, as ROS 2 Jazzy's Ubuntu 24.04 packages are, it waits.)
gdb of a hung node: its main thread in `rmw_destroy_node` -> `destroy_participant` ->
`DomainParticipant::set_listener` -> `system_clock::now`, a receive thread in `onWriterDiscovery` waiting for a
mutex, three more waiting for the PDP's. No Python thread can run meanwhile, and faulthandler's own exit uses code 1.

How: a POSIX timer (`timer_create`, SIGEV_THREAD) whose notification is libc's `_exit` itself, called by glibc in
a thread of its own with the timer's `sigval` as its argument, which holds the code. On the 64-bit little-endian
Linux ABIs (x86-64, aarch64, ppc64le, riscv64) a `union sigval` argument is passed in the first integer register,
where `_exit(int)` reads its status. Elsewhere `exit_after` does nothing and returns False.
"""

from __future__ import annotations

import ctypes
import sys

_SIGEV_THREAD = 2
_CLOCK_MONOTONIC = 1


class _Sigevent(ctypes.Structure):
    """glibc's struct sigevent (64 bytes on 64-bit Linux) with the SIGEV_THREAD member of its union."""

    _fields_ = (
        ("sigev_value", ctypes.c_void_p),
        ("sigev_signo", ctypes.c_int),
        ("sigev_notify", ctypes.c_int),
        ("notify_function", ctypes.c_void_p),
        ("notify_attributes", ctypes.c_void_p),
        ("_pad", ctypes.c_byte * 32),
    )


class _Timespec(ctypes.Structure):
    _fields_ = (("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long))


class _Itimerspec(ctypes.Structure):
    _fields_ = (("it_interval", _Timespec), ("it_value", _Timespec))


def supported() -> bool:
    """Whether this platform passes `_exit` its status as exit_after needs (64-bit little-endian Linux)."""
    return sys.platform == "linux" and sys.byteorder == "little" and ctypes.sizeof(ctypes.c_void_p) == 8


def exit_after(seconds: float, code: int) -> bool:
    """End the process with exit status `code` after `seconds` (monotonic), from a thread glibc starts, whatever the
    other threads are doing; True if the timer is armed. It cannot be cancelled: arm it only once the process's
    exit status is decided. If the process exits first, the timer goes with it."""
    if not supported() or not 0 <= code <= 255:
        return False
    try:
        libc = ctypes.CDLL(None)
        timer_create, timer_settime, exit_now = libc.timer_create, libc.timer_settime, libc._exit
    except (OSError, AttributeError):
        return False
    event = _Sigevent()
    event.sigev_value = code or None
    event.sigev_notify = _SIGEV_THREAD
    event.notify_function = ctypes.cast(exit_now, ctypes.c_void_p).value
    timer = ctypes.c_void_p()
    if timer_create(_CLOCK_MONOTONIC, ctypes.byref(event), ctypes.byref(timer)) != 0:
        return False
    whole = int(seconds)
    spec = _Itimerspec(_Timespec(0, 0), _Timespec(whole, int((seconds - whole) * 1e9)))
    return bool(timer_settime(timer, 0, ctypes.byref(spec), None) == 0)
