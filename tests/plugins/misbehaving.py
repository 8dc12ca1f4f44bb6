"""Navigators whose code misbehaves as a user's might (tests/test_benchmark.py,
tests/test_bad_inputs.py). Most creep like `navigators.creep`, then, at 0.5 s simulated,
take their process down, never return, exit or interrupt; others end the program in their
factory or as their run is built, declare ports that do not fit the station, or write into
the camera image they are given."""

import os
import signal
import sys
import time

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageGrey8U, ImageRgba8U

from plugins.navigators import Creep

# The simulated time at which these navigators misbehave (s).
WHEN = 0.5


class _Crashes(Creep):
    """Kills its own process (as a segfault in a user's extension would end it)."""

    def _calc(self, context, output):
        if context.get_time() >= WHEN:
            os.kill(os.getpid(), signal.SIGKILL)
        super()._calc(context, output)


class _Hangs(Creep):
    """Never returns from computing its command (a user's endless loop)."""

    def _calc(self, context, output):
        if context.get_time() >= WHEN:
            while True:
                time.sleep(0.2)
        super()._calc(context, output)


class _ExitsLater(Creep):
    """Calls sys.exit(0) while computing its command (a user's script's way to stop)."""

    def _calc(self, context, output):
        if context.get_time() >= WHEN:
            sys.exit(0)
        super()._calc(context, output)


class _InterruptsLater(Creep):
    """Raises KeyboardInterrupt itself, no signal involved."""

    def _calc(self, context, output):
        if context.get_time() >= WHEN:
            raise KeyboardInterrupt
        super()._calc(context, output)


class _ShrinksLater(Creep):
    """Sets a command of 3 numbers into its 6-number port."""

    def _calc(self, context, output):
        if context.get_time() >= WHEN:
            output.SetFromVector(np.zeros(3))
            return
        super()._calc(context, output)


def crashes(context):
    return _Crashes(context)


def hangs(context):
    return _Hangs(context)


def exits_later(context):
    return _ExitsLater(context)


def interrupts_later(context):
    return _InterruptsLater(context)


def shrinks_later(context):
    return _ShrinksLater(context)


def exits_in_factory(context):
    sys.exit(0)


class _Ports(LeafSystem):
    """Holds the EPM at its start pose, with its ports changed: `command` declares
    `epm_command` ("short": a vector of 3, "abstract": not a vector), `state_size` its
    `capsule_state` input, `image` an `rgb_image` input ("vector": a vector of 3, "grey": an
    abstract grey image, "rgba": the camera's kind, painted black each time the command is
    computed)."""

    def __init__(self, context, command="", state_size=13, image=""):
        super().__init__()
        self._command = np.asarray(context.start_command, dtype=float)
        self.DeclareVectorInputPort("capsule_state", state_size)
        self._image = None
        if image == "vector":
            self.DeclareVectorInputPort("rgb_image", 3)
        elif image == "grey":
            self.DeclareAbstractInputPort("rgb_image", AbstractValue.Make(ImageGrey8U()))
        elif image == "rgba":
            self._image = self.DeclareAbstractInputPort("rgb_image",
                                                        AbstractValue.Make(ImageRgba8U()))
        if command == "short":
            self.DeclareVectorOutputPort("epm_command", 3, self._calc)
        elif command == "abstract":
            self.DeclareAbstractOutputPort("epm_command", lambda: AbstractValue.Make(0.0),
                                           lambda context, output: None)
        else:
            self.DeclareVectorOutputPort("epm_command", 6, self._calc)

    def _calc(self, context, output):
        if self._image is not None:
            self._image.Eval(context).mutable_data[...] = 0
        output.SetFromVector(self._command[:output.size()])


def short_command(context):
    return _Ports(context, command="short")


def abstract_command(context):
    return _Ports(context, command="abstract")


def long_state(context):
    return _Ports(context, state_size=7)


def image_as_vector(context):
    return _Ports(context, image="vector")


def grey_image(context):
    return _Ports(context, image="grey")


def paints_its_image(context):
    return _Ports(context, image="rgba")


class _ExitsAsItIsBuilt(Creep):
    """Has an output port more, whose value Drake allocates as the run's context is made
    (after the factory has returned): the allocation calls sys.exit(0)."""

    def __init__(self, context):
        super().__init__(context)
        self.DeclareAbstractOutputPort("notes", lambda: sys.exit(0),
                                       lambda context, output: None)


def exits_as_it_is_built(context):
    return _ExitsAsItIsBuilt(context)
