"""int8 versions of the shipped object network by ONNX Runtime's quantisation tools, to compare:

    PYTHONPATH=. python docs/training/experiments/quantisation.py --out /tmp
    python -m bench.compare models service/models/object.onnx /tmp/object-int8-dynamic.onnx /tmp/object-int8-qdq.onnx

Writes the graph after ONNX Runtime's pre-processing (shape inference, the quantiser's input), its
dynamic quantisation (int8 weights, activations quantised at run time) and its static QDQ
quantisation (int8 weights and activations, ranges calibrated on the network's inputs for
jittered ModelNet10 test pairs other than the comparison's: seed 99).
"""

import argparse
from pathlib import Path

from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_dynamic, quantize_static
from onnxruntime.quantization.shape_inference import quant_pre_process

from bench import harness

SOURCE = Path("service/models/object.onnx")


class Calibration(CalibrationDataReader):
    def __init__(self, pairs: int):
        network = harness.Network(SOURCE)
        feeds = [
            network.prepare(p.source, p.target)[0] for p in harness.modelnet_pairs(pairs, "same", "jitter", seed=99)
        ]
        self.feeds = iter(feeds)

    def get_next(self) -> dict | None:
        return next(self.feeds, None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("/tmp"))
    parser.add_argument("--calibration-pairs", type=int, default=16)
    args = parser.parse_args()
    prepared = args.out / "object-preprocessed.onnx"
    quant_pre_process(str(SOURCE), str(prepared), skip_symbolic_shape=True)
    quantize_dynamic(prepared, args.out / "object-int8-dynamic.onnx", weight_type=QuantType.QInt8)
    quantize_static(
        prepared,
        args.out / "object-int8-qdq.onnx",
        Calibration(args.calibration_pairs),
        quant_format=QuantFormat.QDQ,
        activation_type=QuantType.QInt8,
        weight_type=QuantType.QInt8,
        op_types_to_quantize=["MatMul", "Gemm", "Conv"],
    )
    print(f"wrote {prepared.name}, object-int8-dynamic.onnx and object-int8-qdq.onnx to {args.out}")


if __name__ == "__main__":
    main()
