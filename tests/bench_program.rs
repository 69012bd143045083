//! `ecm-lcd-bench speed` end to end as a user runs it, on small sizes: the sections run, `--json` parses, and the
//! ONNX export of the project's weights computes the same feature map as ecm-lcd (within 1e-4). The ONNX
//! Runtime check creates `target/bench-venv` on its first run (needs PyPI then), like `io_fixtures.rs`.

use std::path::{Path, PathBuf};
use std::process::Command;

fn tflite() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared");
    assert!(dir.join("models").is_dir(), "shared data missing at {}: tests need ../shared (see README)", dir.display());
    dir.join("models/mobilenet_v2_1.0_224_quant.tflite")
}

fn bench_json(cache: &Path, args: &[&str]) -> serde_json::Value {
    let out = Command::new(env!("CARGO_BIN_EXE_ecm-lcd-bench"))
        .arg("speed")
        .args(args)
        .arg("--json")
        .env("ECM_LCD_CACHE", cache)
        .env_remove("ECM_LCD_WEIGHTS")
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    assert!(out.status.success(), "ecm-lcd-bench speed {args:?} failed: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("bench printed no JSON ({e}): {}", String::from_utf8_lossy(&out.stdout)))
}

#[test]
fn onnx_export_of_the_weights_equals_ecm_lcd() {
    let cache = tempfile::tempdir().unwrap();
    let weights = tflite();
    let report = bench_json(
        cache.path(),
        &["--only", "ort", "--weights", weights.to_str().unwrap(), "--runs", "2", "--threads", "1"],
    );
    let archs = report["ort"]["archs"].as_array().expect("an ort section");
    assert_eq!(archs.len(), 2, "{report}");
    for arch in archs {
        let diff = arch["max_abs_diff"].as_f64().unwrap();
        assert!(diff <= 1e-4, "{}: ONNX Runtime differs from ecm-lcd by {diff}", arch["arch"]);
        let timing = &arch["timings"][0];
        assert_eq!(timing["threads"], 1);
        assert!(timing["median_ms"].as_f64().unwrap() > 0.0, "{arch}");
    }
    assert!(report["goals"].as_array().unwrap().iter().any(|g| g["goal"].as_str().unwrap().contains("within 1e-4")));
}

#[test]
fn search_and_memory_sections_report_exact_and_indexed_search() {
    let cache = tempfile::tempdir().unwrap();
    let report = bench_json(
        cache.path(),
        &[
            "--only",
            "search,memory",
            "--search-sizes",
            "1000,8000",
            "--search-dims",
            "400",
            "--search-coded-dims",
            "400",
            "--queries",
            "20",
            "--memory",
            "7000:400",
        ],
    );
    let rows = report["search"].as_array().unwrap();
    assert_eq!(rows.len(), 4, "{report}");
    // 1000 x 400 is below the index threshold (exact), 8000 x 400 above it (IVF); f32 rows first,
    // then six-level codes of the same vectors.
    for (row, storage) in rows.iter().zip(["f32", "f32", "levels6", "levels6"]) {
        assert_eq!(row["storage"], storage, "{row}");
        assert!(row["auto_on_two_threads"]["median_ms"].as_f64().unwrap() > 0.0, "{row}");
    }
    for pair in rows.chunks(2) {
        assert_eq!(pair[0]["auto_method"], "exact");
        assert_eq!(pair[0]["recall"], 1.0);
        assert_eq!(pair[1]["auto_method"], "ivf");
        assert!(pair[1]["recall"].as_f64().unwrap() >= 0.99, "{}", pair[1]);
    }
    // Coded rows are also compared with the exact search of the f32 vectors they code.
    assert!(rows[0]["recall_vs_f32"].is_null() && rows[3]["recall_vs_f32"].as_f64().unwrap() > 0.0, "{report}");
    let memory = &report["memory"][0];
    assert_eq!(memory["stored"], 7000);
    assert_eq!(memory["indexed"], true);
    // 400 values take 1600 bytes as f32, so the default storage codes them: 134 code bytes and three
    // factors a row, 7000 x 146 bytes. The peak includes at least the rows.
    assert_eq!(memory["storage"], "levels6");
    assert!((memory["descriptors_mb"].as_f64().unwrap() - 1.022).abs() < 1e-9, "{memory}");
    let (baseline, peak) = (memory["baseline_mb"].as_f64().unwrap(), memory["peak_mb"].as_f64().unwrap());
    assert!(peak >= baseline + 1.022, "{memory}");
}

#[test]
fn end_to_end_section_times_a_raw_a_jpeg_and_a_verified_keyframe() {
    let cache = tempfile::tempdir().unwrap();
    let weights = tflite();
    let report = bench_json(
        cache.path(),
        &["--only", "e2e", "--weights", weights.to_str().unwrap(), "--e2e-stored", "3000", "--runs", "20"],
    );
    let rows = report["end_to_end"].as_array().expect("an end_to_end section");
    let inputs: Vec<&str> = rows.iter().map(|r| r["input"].as_str().unwrap()).collect();
    assert_eq!(inputs, ["rgb8", "jpeg", "rgb8, verified"], "{report}");
    for row in rows {
        assert_eq!(row["stored"], 3000);
        // The bench times at least 100 keyframes of each input.
        assert!(row["total"]["runs"].as_u64().unwrap() >= 100, "{row}");
        let (total, network, detector) = (
            row["total"]["median_ms"].as_f64().unwrap(),
            row["network"]["median_ms"].as_f64().unwrap(),
            row["detector"]["median_ms"].as_f64().unwrap(),
        );
        assert!(network > 0.0 && detector > 0.0 && total >= network + detector, "{row}");
        let verified = row["input"] == "rgb8, verified";
        assert_eq!(row["verification"]["median_ms"].as_f64().is_some_and(|ms| ms > 0.0), verified, "{row}");
    }
    let goals: Vec<&str> = report["goals"].as_array().unwrap().iter().map(|g| g["goal"].as_str().unwrap()).collect();
    assert!(
        goals.iter().any(|g| g.starts_with("keyframe (rgb8)"))
            && goals.iter().any(|g| g.starts_with("keyframe (jpeg)")),
        "{goals:?}"
    );
}
