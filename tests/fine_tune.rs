//! Fine-tuning from the pretrained weights on real images: two indoor scenes of the shared TUM
//! frames (fr3 office, fr2 desk) as two class folders, every fourth frame held out, trained with
//! the command a new user runs. Folded BatchNorm frozen, a zero-initialised head and a slower
//! body (`ecm-lcd train` with `--init`) keep what the ImageNet weights know.

mod support;

use std::path::Path;

/// The two-scene folder: `office/` and `desk/` linked to the shared frames, with
/// `TrainImages.txt` / `TestImages.txt` (28 train, 9 held out). Returns the held-out paths.
fn two_scenes(root: &Path) -> Vec<String> {
    let tum = support::shared_dir().join("data/tum");
    let (mut train, mut test) = (String::new(), String::new());
    for (class, sequence) in [("office", "fr3_long_office_household"), ("desk", "fr2_desk")] {
        std::fs::create_dir_all(root.join(class)).unwrap();
        let mut frames: Vec<_> =
            std::fs::read_dir(tum.join(sequence).join("rgb")).unwrap().map(|e| e.unwrap().path()).collect();
        frames.sort();
        for (i, frame) in frames.iter().enumerate() {
            let name = format!("{class}/{}", frame.file_name().unwrap().to_str().unwrap());
            std::os::unix::fs::symlink(frame, root.join(&name)).unwrap();
            let list = if i % 4 == 3 { &mut test } else { &mut train };
            list.push_str(&name);
            list.push('\n');
        }
    }
    std::fs::write(root.join("TrainImages.txt"), train).unwrap();
    std::fs::write(root.join("TestImages.txt"), &test).unwrap();
    test.lines().map(str::to_string).collect()
}

#[test]
fn fine_tuning_two_real_scenes_keeps_the_pretrained_features() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let held_out = two_scenes(&data);
    assert_eq!(held_out.len(), 9);
    let path = |p: &Path| p.to_str().unwrap().to_string();
    let init = dir.path().join("mnv2.safetensors");
    let tflite = support::shared_dir().join("models/mobilenet_v2_1.0_224_quant.tflite");
    support::ecm_lcd_ok(&["import-weights", &path(&tflite), "-o", &path(&init)]);
    let out = dir.path().join("run.safetensors");
    support::ecm_lcd_ok(&[
        "--threads",
        "2",
        "train",
        "--data",
        &path(&data),
        "--init",
        &path(&init),
        "--arch",
        "ecmobilenet",
        "--size",
        "128",
        "--batch",
        "8",
        "--optimizer",
        "adamw",
        "--lr",
        "1e-3",
        "--epochs",
        "8",
        "-o",
        &path(&out),
    ]);
    let record: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("run.json")).unwrap()).unwrap();
    let history = record["history"].as_array().unwrap();
    assert_eq!(history.len(), 8);
    assert_eq!(record["steps_done"], 32);
    let losses: Vec<f64> = history.iter().map(|e| e["train_loss"].as_f64().unwrap()).collect();
    let last = history.last().unwrap();
    // Held out: at least 8 of 9 after the last epoch, and the loss well below ln 2 (one class).
    assert!(last["val_accuracy"].as_f64().unwrap() >= 8.0 / 9.0 - 1e-9, "held-out accuracy: {history:?}");
    assert!(*losses.last().unwrap() < 0.4, "training loss {losses:?}");

    // `classify` with the trained weights names each held-out image's folder.
    let images: Vec<String> = held_out.iter().map(|name| path(&data.join(name))).collect();
    let mut args = vec!["classify", "--weights", out.to_str().unwrap(), "--size", "128", "--top", "1", "--json"];
    args.extend(images.iter().map(String::as_str));
    let answer: serde_json::Value = serde_json::from_slice(&support::ecm_lcd_ok(&args).stdout).unwrap();
    let named: Vec<(String, String)> = answer
        .as_array()
        .unwrap()
        .iter()
        .map(|a| (a["image"].as_str().unwrap().to_string(), a["top"][0]["label"].as_str().unwrap().to_string()))
        .collect();
    let right = named.iter().filter(|(image, label)| image.contains(&format!("/{label}/"))).count();
    assert!(right >= 8, "classify named {named:?}");
}
