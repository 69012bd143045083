//! The networks with real weights, through the command line as a user runs them: ImageNet
//! classification against the TFLite reference, fast kernels against stock candle, the weights
//! resolution chain (including the download path, against a loopback server) and bad input.

use std::io::{Read, Write};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use candle_core::{Device, Tensor};
use ecm_lcd::model::layers::Mode;
use ecm_lcd::model::weights::resolve;
use ecm_lcd::model::Arch;

fn shared() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared");
    assert!(dir.join("models").is_dir(), "shared data missing at {}: tests need ../shared (see README)", dir.display());
    dir
}

fn tflite() -> PathBuf {
    shared().join("models/mobilenet_v2_1.0_224_quant.tflite")
}

/// `ecm-lcd ARGS` with a private weights cache.
fn ecm_lcd(cache: &Path, args: &[&str]) -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_ecm-lcd"));
    cmd.args(args).env("ECM_LCD_CACHE", cache).env_remove("ECM_LCD_WEIGHTS").env("RUST_LOG", "warn");
    cmd
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A failing command printed one `error:` line naming `needle`, and did not panic.
fn assert_clean_failure(out: &Output, needle: &str) {
    let err = stderr(out);
    assert!(!out.status.success(), "expected failure, got success; stderr: {err}");
    assert!(!err.contains("panicked"), "panicked: {err}");
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(lines.len(), 1, "expected one error line: {err}");
    assert!(lines[0].contains(needle), "error does not name {needle}: {err}");
}

#[test]
fn classify_matches_the_tflite_reference() {
    let cache = tempfile::tempdir().unwrap();
    let images = shared().join("data/imagenet");
    // (file, top-1 index, probability from the TFLite runtime on the int8 model)
    let reference = [
        ("cat.bmp", 286, 0.789),
        ("grace_hopper.bmp", 653, 0.922),
        ("bird.bmp", 20, 0.988),
        ("dragonfly.bmp", 320, 0.984),
    ];
    let paths: Vec<String> = reference.iter().map(|(f, _, _)| images.join(f).display().to_string()).collect();
    let mut args = vec!["classify", "--json"];
    args.extend(paths.iter().map(String::as_str));
    let out = ecm_lcd(cache.path(), &args).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    for (result, (file, index, prob)) in json.as_array().unwrap().iter().zip(reference) {
        assert!(result["image"].as_str().unwrap().ends_with(file));
        let top = &result["top"][0];
        assert_eq!(top["index"], index, "{file}: {result}");
        let p = top["prob"].as_f64().unwrap();
        assert!((p - prob).abs() <= 0.05, "{file}: p={p}, reference {prob}");
        assert_eq!(result["top"].as_array().unwrap().len(), 5);
    }
    // The import was cached for the next command.
    assert!(cache.path().join(resolve::CACHED_WEIGHTS).is_file());
    // A labels file that does not name every class is refused, not half used.
    let short = cache.path().join("two_labels.txt");
    std::fs::write(&short, "a\nb\n").unwrap();
    let out = ecm_lcd(cache.path(), &["classify", "--labels", short.to_str().unwrap(), &paths[0]]).output().unwrap();
    assert_clean_failure(&out, "names 2 classes, the network has 1001");
}

#[test]
fn fast_kernels_equal_stock_candle_on_whole_networks() {
    let weights = resolve::load_file(&tflite()).unwrap().weights;
    let image = ecm_lcd::preprocess::read_image(&shared().join("data/imagenet/grace_hopper.bmp")).unwrap();
    let x = ecm_lcd::preprocess::Preprocessor::new(224).tensor(&image).unwrap();
    for arch in [Arch::MobileNetV2, Arch::EcMobileNet] {
        let net = weights.for_arch(arch).unwrap().network(false).unwrap();
        assert!(net.is_planned(), "{arch}: folded constant weights run the inference plan");
        let fast = net.features(&x, Mode::Inference).unwrap();
        let reference = net.features(&x, Mode::Reference).unwrap();
        assert_eq!(fast.dims(), &[1, 1280, 7, 7]);
        let max = reference.abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap();
        let diff = (fast - reference)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        // 1e-4 relative to the largest activation: float summation order differs, nothing else.
        assert!(diff <= 1e-4 * max.max(1.0), "{arch}: max diff {diff} (largest value {max})");
    }
}

#[test]
fn any_input_size_that_is_a_multiple_of_32_works() {
    let net =
        resolve::load_file(&tflite()).unwrap().weights.for_arch(Arch::EcMobileNet).unwrap().network(false).unwrap();
    for size in [160usize, 256] {
        let x = Tensor::zeros((1, 3, size, size), candle_core::DType::F32, &Device::Cpu).unwrap();
        assert_eq!(net.features(&x, Mode::Inference).unwrap().dims(), &[1, 1280, size / 32, size / 32]);
    }
    assert!(ecm_lcd::model::check_input_size(100).is_err());
}

#[test]
fn import_weights_writes_files_that_load() {
    let dir = tempfile::tempdir().unwrap();
    for arch in ["mobilenetv2", "ecmobilenet"] {
        let out_path = dir.path().join(format!("{arch}.safetensors"));
        let out = ecm_lcd(
            dir.path(),
            &["import-weights", tflite().to_str().unwrap(), "-o", out_path.to_str().unwrap(), "--arch", arch],
        )
        .output()
        .unwrap();
        assert!(out.status.success(), "{}", stderr(&out));
        let loaded = resolve::load_file(&out_path).unwrap();
        assert_eq!(loaded.weights.arch.name(), arch);
        assert_eq!(loaded.weights.classes, Some(1001));
        loaded.weights.network(true).unwrap();
    }
    // Classification through the saved MobileNetV2 file gives the reference class.
    let mnv2 = dir.path().join("mobilenetv2.safetensors");
    let bird = shared().join("data/imagenet/bird.bmp");
    let out = ecm_lcd(
        dir.path(),
        &["classify", "--json", "--arch", "mobilenetv2", "--weights", mnv2.to_str().unwrap(), bird.to_str().unwrap()],
    )
    .output()
    .unwrap();
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(json[0]["top"][0]["index"], 20);
    // One network, one identity (the keyframe database's): the TFLite file read directly, a copy of
    // it under another name, its import saved by `import-weights`, and the cache's import.
    let copy = dir.path().join("renamed.tflite");
    std::fs::copy(tflite(), &copy).unwrap();
    let cache = dir.path().join("cache");
    std::fs::create_dir(&cache).unwrap();
    let cached =
        ecm_lcd(&cache, &["classify", bird.to_str().unwrap()]).env("ECM_LCD_SHARED", shared()).output().unwrap();
    assert!(cached.status.success(), "{}", stderr(&cached));
    let identities: Vec<String> = [tflite(), copy, mnv2, cache.join(resolve::CACHED_WEIGHTS)]
        .iter()
        .map(|path| resolve::load_file(path).unwrap().sha256)
        .collect();
    assert!(identities.iter().all(|id| *id == identities[0]), "{identities:?}");
}

#[test]
fn model_info_reports_params_and_macs() {
    let dir = tempfile::tempdir().unwrap();
    let info = |arch: &str, classes: &str| -> serde_json::Value {
        let out =
            ecm_lcd(dir.path(), &["model-info", "--arch", arch, "--classes", classes, "--json"]).output().unwrap();
        serde_json::from_slice(&out.stdout).unwrap()
    };
    // torchvision's MobileNetV2 has 3,504,872 parameters with 1000 classes.
    let mnv2 = info("mobilenetv2", "1000");
    assert_eq!(mnv2["params"], 3_504_872);
    assert_eq!(mnv2["arch"], "mobilenetv2");
    let (m, e) = (info("mobilenetv2", "67"), info("ecmobilenet", "67"));
    assert!(e["params"].as_u64() < m["params"].as_u64());
    assert!(e["macs"].as_u64() < m["macs"].as_u64());
}

#[test]
fn bad_inputs_give_one_line_errors_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let cat = shared().join("data/imagenet/cat.bmp");
    let cat = cat.to_str().unwrap();
    let run = |args: &[&str]| ecm_lcd(dir.path(), args).output().unwrap();

    let missing = dir.path().join("missing.safetensors");
    assert_clean_failure(&run(&["classify", "--weights", missing.to_str().unwrap(), cat]), "missing.safetensors");

    let corrupt = dir.path().join("corrupt.safetensors");
    std::fs::write(&corrupt, b"\x10\x00\x00\x00\x00\x00\x00\x00{not json}......").unwrap();
    assert_clean_failure(&run(&["classify", "--weights", corrupt.to_str().unwrap(), cat]), "corrupt.safetensors");

    let truncated = dir.path().join("truncated.tflite");
    let bytes = std::fs::read(tflite()).unwrap();
    std::fs::write(&truncated, &bytes[..bytes.len() / 3]).unwrap();
    assert_clean_failure(&run(&["classify", "--weights", truncated.to_str().unwrap(), cat]), "truncated.tflite");

    let text = dir.path().join("notes.png");
    std::fs::write(&text, b"this is not an image").unwrap();
    assert_clean_failure(&run(&["classify", text.to_str().unwrap()]), "notes.png");
    assert_clean_failure(&run(&["classify", "/nonexistent/photo.jpg"]), "photo.jpg");
    assert_clean_failure(&run(&["model-info", "--size", "100"]), "100");
}

/// Serves `body` to `requests` HTTP GETs on loopback; returns the address.
fn serve(body: Vec<u8>, requests: usize) -> String {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    std::thread::spawn(move || {
        for stream in listener.incoming().take(requests) {
            let mut stream = stream.unwrap();
            let mut buf = [0u8; 4096];
            let _ = stream.read(&mut buf);
            let head = format!("HTTP/1.1 200 OK\r\nContent-Length: {}\r\nConnection: close\r\n\r\n", body.len());
            let _ = stream.write_all(head.as_bytes()).and_then(|_| stream.write_all(&body));
        }
    });
    format!("http://{addr}/{}", resolve::UPSTREAM_FILE)
}

#[test]
fn weights_are_downloaded_checked_and_cached_when_nothing_local_exists() {
    let cache = tempfile::tempdir().unwrap();
    let empty_shared = tempfile::tempdir().unwrap();
    let cat = shared().join("data/imagenet/cat.bmp");
    let labels = shared().join("data/imagenet/imagenet_labels.txt");
    let classify = |url: &str, offline: bool| {
        let mut cmd =
            ecm_lcd(cache.path(), &["classify", "--json", "--labels", labels.to_str().unwrap(), cat.to_str().unwrap()]);
        cmd.env("ECM_LCD_SHARED", empty_shared.path()).env("ECM_LCD_WEIGHTS_URL", url);
        if offline {
            cmd.env("ECM_LCD_OFFLINE", "1");
        }
        cmd.output().unwrap()
    };

    // Offline with nothing local: the error says what is missing and how to get it.
    let out = classify("http://127.0.0.1:9/none", true);
    assert_clean_failure(&out, resolve::UPSTREAM_FILE);
    assert!(stderr(&out).contains(resolve::UPSTREAM_SHA256));

    // A server that sends the wrong bytes: refused by the checksum, nothing cached.
    let out = classify(&serve(b"not the model".to_vec(), 1), false);
    assert_clean_failure(&out, "SHA-256");
    assert!(!cache.path().join(resolve::UPSTREAM_FILE).exists());

    // The real file: downloaded, verified, imported, cached; classification works.
    let out = classify(&serve(std::fs::read(tflite()).unwrap(), 1), false);
    assert!(out.status.success(), "{}", stderr(&out));
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(json[0]["top"][0]["index"], 286);
    assert!(cache.path().join(resolve::UPSTREAM_FILE).is_file());
    assert!(cache.path().join(resolve::CACHED_WEIGHTS).is_file());

    // Next time the cache answers: no server needed.
    let out = classify("http://127.0.0.1:9/unreachable", false);
    assert!(out.status.success(), "{}", stderr(&out));
}

#[test]
fn embed_writes_a_header_and_one_row_per_image() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("descriptors.csv");
    let images = ["bird.bmp", "cat.bmp"].map(|name| shared().join("data/imagenet").join(name));
    let mut args = vec!["embed".to_string(), "-o".into(), csv.to_str().unwrap().into()];
    args.extend(images.iter().map(|p| p.to_str().unwrap().to_string()));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let out = ecm_lcd(dir.path(), &args).env("ECM_LCD_SHARED", shared()).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&csv).unwrap();
    let rows: Vec<Vec<&str>> = text.lines().map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 3, "a header and two rows");
    assert_eq!((rows[0][0], rows[0][1], rows[0][1280], rows[0].len()), ("image", "v0", "v1279", 1281));
    for (row, image) in rows[1..].iter().zip(&images) {
        assert_eq!((row[0], row.len()), (image.to_str().unwrap(), 1281));
        assert!(row[1..].iter().all(|v| v.parse::<f32>().is_ok_and(f32::is_finite)));
    }
    // The weights are an input too, whether named by --weights or by $ECM_LCD_WEIGHTS (here a
    // TFLite model under another extension, known by its content).
    let weights = dir.path().join("w.model");
    std::fs::copy(tflite(), &weights).unwrap();
    let (weights, image) = (weights.to_str().unwrap(), images[0].to_str().unwrap());
    let out = ecm_lcd(dir.path(), &["embed", "--weights", weights, image, "-o", weights]).output().unwrap();
    assert!(!out.status.success() && stderr(&out).contains("destroy the input"), "{}", stderr(&out));
    let out = ecm_lcd(dir.path(), &["embed", image, "-o", weights]).env("ECM_LCD_WEIGHTS", weights).output().unwrap();
    assert!(!out.status.success() && stderr(&out).contains("destroy the input"), "{}", stderr(&out));
    assert_eq!(std::fs::read(weights).unwrap(), std::fs::read(tflite()).unwrap(), "the weights changed");
}
