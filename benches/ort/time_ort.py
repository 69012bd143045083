"""Times an ONNX model in ONNX Runtime the way `ecm-lcd-bench speed` times its own network, and checks that
it computes the same output.

--input / --expected: raw little-endian f32 files (the preprocessed frame and ecm-lcd's output on it).
For each thread count (intra_op_num_threads, inter_op 1, sequential execution, all graph optimisations),
runs `--warmup` untimed then `--runs` timed inferences at batch 1 and reports median and p90 in ms.
Prints one JSON object: {"onnxruntime": version, "max_abs_diff": ..., "timings": [{"threads", "median_ms",
"p90_ms", "runs"}]}.
"""
import argparse
import json
import time

import numpy as np
import onnxruntime as ort


def quantile(samples, q):
    s = sorted(samples)
    return s[round((len(s) - 1) * q)]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--input", required=True)
    parser.add_argument("--expected", required=True)
    parser.add_argument("--size", type=int, default=224)
    parser.add_argument("--threads", default="1,2")
    parser.add_argument("--runs", type=int, default=50)
    parser.add_argument("--warmup", type=int, default=5)
    args = parser.parse_args()
    ort.set_default_logger_severity(3)
    x = np.fromfile(args.input, dtype="<f4").reshape(1, 3, args.size, args.size)
    expected = np.fromfile(args.expected, dtype="<f4")
    result = {"onnxruntime": ort.__version__, "timings": []}
    for threads in [int(t) for t in args.threads.split(",")]:
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        session = ort.InferenceSession(args.model, options, providers=["CPUExecutionProvider"])
        out = session.run(["features"], {"input": x})[0].ravel()
        if expected.size != out.size:
            raise SystemExit(f"ONNX output has {out.size} values, ecm-lcd's {expected.size}")
        result["max_abs_diff"] = max(result.get("max_abs_diff", 0.0), float(np.max(np.abs(out - expected))))
        for _ in range(args.warmup):
            session.run(["features"], {"input": x})
        samples = []
        for _ in range(args.runs):
            start = time.perf_counter()
            session.run(["features"], {"input": x})
            samples.append((time.perf_counter() - start) * 1e3)
        result["timings"].append({"threads": threads, "runs": args.runs, "median_ms": quantile(samples, 0.5), "p90_ms": quantile(samples, 0.9)})
    print(json.dumps(result))


if __name__ == "__main__":
    main()
