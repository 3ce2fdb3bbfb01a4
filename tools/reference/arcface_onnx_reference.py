"""A tiny ONNX face-recognition-style network and its output, for `crates/metrics`'s ONNX
reader and graph runner (`src/onnx.rs`, `src/arcface.rs`).

The graph uses every operator the runner supports, in the shapes InsightFace's IResNet exports
use them (input normalisation by Sub/Mul, Conv with bias, strides, groups, dilations and
asymmetric pads, Constant nodes (int64 and float), BatchNormalization on 4-D and 2-D inputs, PRelu with [C, 1, 1] slopes, residual
Add, Relu, Reshape with 0 / -1, Flatten, Gemm with transB, Dropout, Identity, Div, MatMul,
GlobalAveragePool), with seeded random weights. Its output on a fixed input is computed by the
`onnx` package's own reference evaluator (`onnx.reference.ReferenceEvaluator`), which is
independent of our code. Opset 15: BatchNormalization-15 runs in inference mode by default
(the evaluator's BatchNormalization-9 folds batch statistics in when the schema's default
momentum is filled in, which is not what an exported network computes).

Writes `arcface_tiny.onnx` and `arcface_tiny.json` (the output) into the golden folder:

    pip install onnx==1.23.2 numpy==1.26.4
    python3 tools/reference/arcface_onnx_reference.py crates/metrics/tests/golden

The input is `x[i] = 0.9 * sin(0.37 * i)` over the flat [1, 3, 112, 112] tensor, in float32 (the
Rust test builds the same values).
"""

import json
import sys
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper
from onnx.reference import ReferenceEvaluator


def main(out: Path) -> None:
    rng = np.random.default_rng(21)

    def w(*shape, scale=0.3):
        return (rng.standard_normal(shape) * scale).astype(np.float32)

    inits = {
        "mean": np.full((1, 3, 1, 1), 0.1, np.float32),
        "scale": np.array([1.5, 0.8, 1.1], np.float32).reshape(1, 3, 1, 1),
        "c1.w": w(8, 3, 3, 3), "c1.b": w(8),
        "bn1.s": (1 + w(8, scale=0.1)), "bn1.b": w(8), "bn1.m": w(8), "bn1.v": (0.5 + np.abs(w(8))),
        "pr1": w(8, 1, 1, scale=0.2),
        "c2.w": w(8, 4, 3, 3),
        "sc.w": w(8, 8, 1, 1),
        "c3.w": w(8, 8, 3, 3),
        "c4.w": w(8, 8, 4, 4), "c4.b": w(8),
        "fc.w": w(16, 392, scale=0.05), "fc.b": w(16),
        "bn2.s": (1 + w(16, scale=0.1)), "bn2.b": w(16), "bn2.m": w(16), "bn2.v": (0.5 + np.abs(w(16))),
        "proj": w(16, 8),
        "gw": w(8, 8, 1, 1),
    }
    N = helper.make_node
    nodes = [
        # Constants as nodes (as torch exports write them) rather than initializers.
        N("Constant", [], ["shape"], name="shape_const",
          value=numpy_helper.from_array(np.array([0, -1], np.int64), "shape_value")),
        N("Constant", [], ["two"], name="two_const",
          value=numpy_helper.from_array(np.array([2.0], np.float32), "two_value")),
        N("Sub", ["data", "mean"], ["n0"], name="sub"),
        N("Mul", ["n0", "scale"], ["n1"], name="mul"),
        N("Conv", ["n1", "c1.w", "c1.b"], ["a1"], name="conv1", kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1]),
        N("BatchNormalization", ["a1", "bn1.s", "bn1.b", "bn1.m", "bn1.v"], ["a2"], name="bn1", epsilon=2e-5),
        N("PRelu", ["a2", "pr1"], ["a3"], name="prelu1"),
        # 56 -> 28, asymmetric pads, two groups.
        N("Conv", ["a3", "c2.w"], ["b1"], name="conv2", kernel_shape=[3, 3], strides=[2, 2], pads=[0, 0, 1, 1], group=2),
        N("Conv", ["a3", "sc.w"], ["b2"], name="shortcut", kernel_shape=[1, 1], strides=[2, 2]),
        N("Add", ["b1", "b2"], ["b3"], name="add"),
        N("Relu", ["b3"], ["b4"], name="relu"),
        N("Conv", ["b4", "c3.w"], ["b5"], name="conv3", kernel_shape=[3, 3], pads=[2, 2, 2, 2], dilations=[2, 2]),
        N("Conv", ["b5", "c4.w", "c4.b"], ["d1"], name="conv4", kernel_shape=[4, 4], strides=[4, 4]),
        N("Dropout", ["d1"], ["d2"], name="dropout"),
        N("Reshape", ["d2", "shape"], ["e1"], name="reshape"),
        N("Gemm", ["e1", "fc.w", "fc.b"], ["e2"], name="fc", transB=1, alpha=0.5, beta=2.0),
        N("BatchNormalization", ["e2", "bn2.s", "bn2.b", "bn2.m", "bn2.v"], ["e3"], name="features"),
        N("Div", ["e3", "two"], ["e4"], name="div"),
        N("Identity", ["e4"], ["e5"], name="identity"),
        N("MatMul", ["e5", "proj"], ["f1"], name="matmul"),
        # A side branch joined back: GlobalAveragePool and Flatten over the conv features.
        N("Conv", ["d1", "gw"], ["g1"], name="gconv", kernel_shape=[1, 1]),
        N("GlobalAveragePool", ["g1"], ["g2"], name="gap"),
        N("Flatten", ["g2"], ["g3"], name="flatten", axis=1),
        N("Add", ["f1", "g3"], ["embedding"], name="out"),
    ]
    graph = helper.make_graph(
        nodes,
        "tiny_arcface",
        [helper.make_tensor_value_info("data", TensorProto.FLOAT, [1, 3, 112, 112])],
        [helper.make_tensor_value_info("embedding", TensorProto.FLOAT, [1, 8])],
        initializer=[numpy_helper.from_array(v, k) for k, v in inits.items()],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 15)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    i = np.arange(3 * 112 * 112, dtype=np.float64)
    x = (0.9 * np.sin(0.37 * i)).astype(np.float32).reshape(1, 3, 112, 112)
    (y,) = ReferenceEvaluator(model).run(None, {"data": x})
    out.mkdir(parents=True, exist_ok=True)
    onnx.save(model, out / "arcface_tiny.onnx")
    (out / "arcface_tiny.json").write_text(json.dumps({
        "source": "tools/reference/arcface_onnx_reference.py (onnx %s ReferenceEvaluator)" % onnx.__version__,
        "input": "x[i] = 0.9 * sin(0.37 * i), float32, [1, 3, 112, 112]",
        "output": [float(v) for v in y.ravel()],
    }, indent=1) + "\n")
    print("wrote", out / "arcface_tiny.onnx", y.ravel())


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "crates/metrics/tests/golden"))
