"""MediaPipe Hands imported quietly, and its graph tuned for our use (mediapipe 0.10.21).

:func:`hands_module` imports ``mediapipe.solutions.hands`` (the legacy API whose palm and
landmark models ship inside the wheel) with its glog/absl chatter on stderr swallowed.
:func:`tuned_hands` returns a ``Hands`` subclass that

- sets the threads of both TFLite inferences (the legacy API has no such option: it is
  written into the two ``InferenceCalculator`` nodes' XNNPACK delegate through the hook
  ``SolutionBase`` calls on the expanded graph before starting it; MediaPipe's own default
  on desktop Linux is 1, and ``OMP_NUM_THREADS`` does not reach TFLite);
- has a leaner ``process``: the base class builds a new namedtuple class per call and
  converts all three outputs; this one returns :class:`HandsOutput` with the two outputs
  we read. The graph and its outputs are the same (tested against the plain ``Hands``);
- splits ``process`` into ``send`` and ``wait``, so that a caller can turn one frame's
  output into arrays while the graph already runs on the next.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
from collections.abc import Iterator
from typing import Any, NamedTuple

import numpy as np

_NOISE = re.compile(
    r"XNNPACK delegate|absl::InitializeLog|inference_feedback_manager|"
    r"landmark_projection_calculator|^\s*$"
)
_HANDS: Any = None
_TUNED: Any = None


class HandsOutput(NamedTuple):
    """What :meth:`process` returns: MediaPipe's protobuf lists, None when no hand."""

    multi_hand_landmarks: list | None
    multi_handedness: list | None


@contextlib.contextmanager
def quiet_stderr() -> Iterator[None]:
    """Send fd 2 to a file while MediaPipe starts; lines that are not its known start-up
    chatter are written back to stderr afterwards."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            for line in sink.read().decode(errors="replace").splitlines():
                if not _NOISE.search(line):
                    print(line, file=sys.stderr)


def hands_module() -> Any:
    """``mediapipe.solutions.hands``, imported on first call with its log chatter hidden."""
    global _HANDS
    if _HANDS is None:
        os.environ.setdefault("GLOG_minloglevel", "2")
        os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
        with quiet_stderr():
            from mediapipe.python.solutions import hands
        _HANDS = hands
    return _HANDS


def tuned_hands() -> Any:
    """The ``Hands`` subclass: ``TunedHands(inference_threads=n, **Hands_kwargs)``."""
    global _TUNED
    if _TUNED is not None:
        return _TUNED
    from mediapipe.calculators.tensor.inference_calculator_pb2 import InferenceCalculatorOptions
    from mediapipe.python import packet_creator, packet_getter
    from mediapipe.python._framework_bindings.image_frame import ImageFormat

    class TunedHands(hands_module().Hands):  # type: ignore[misc,name-defined]
        def __init__(self, *, inference_threads: int, **kwargs: Any):
            self._inference_threads = inference_threads
            super().__init__(**kwargs)
            (self._input,) = self._input_stream_type_info  # "image"

        def _modify_calculator_options(self, graph: Any, params: Any) -> None:
            super()._modify_calculator_options(graph, params)
            nodes = [n for n in graph.node if n.calculator.startswith("InferenceCalculator")]
            if len(nodes) != 2:  # palm + landmark model; another wheel, another graph
                raise RuntimeError(f"expected 2 inference nodes in the hands graph, found "
                                   f"{len(nodes)}: not mediapipe 0.10.21's graph?")
            for node in nodes:
                options = node.options.Extensions[InferenceCalculatorOptions.ext]
                options.delegate.xnnpack.num_threads = self._inference_threads

        def process(self, image: np.ndarray) -> HandsOutput:
            """Hands in an ``(h, w, 3) uint8`` RGB image (read-only: taken by reference)."""
            self.send(image)
            return self.outputs(self.wait())

        def send(self, image: np.ndarray) -> None:
            """Start the graph on ``image``; :meth:`wait` returns when it is done."""
            if image.ndim != 3 or image.shape[2] != 3:
                raise ValueError("Input image must contain three channel rgb data.")
            self._simulated_timestamp += 33333  # 30 fps, as the base class
            packet = packet_creator.create_image_frame(image, image_format=ImageFormat.SRGB)
            self._graph.add_packet_to_input_stream(
                stream=self._input, packet=packet.at(self._simulated_timestamp))

        def wait(self) -> dict[str, Any]:
            """The output packets of the image last sent (unconverted: :meth:`outputs` may
            run while the graph works on the next image)."""
            self._graph.wait_until_idle()
            packets = dict(self._graph_outputs)
            self._graph_outputs.clear()
            return packets

        @staticmethod
        def outputs(packets: dict[str, Any]) -> HandsOutput:
            out = []
            for name in HandsOutput._fields:
                found = packets.get(name)
                empty = found is None or found.is_empty()
                out.append(None if empty else packet_getter.get_proto_list(found))
            return HandsOutput(*out)

    _TUNED = TunedHands
    return _TUNED
