//! `ecm-lcd train-place` end to end on a small synthetic sequence: the triplet loss falls over the
//! epochs, and the weights it writes run the detector (`replay --weights`).

mod support;

#[test]
fn place_training_lowers_the_triplet_loss_and_its_weights_replay() {
    let dir = tempfile::tempdir().unwrap();
    let path = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    support::ecm_lcd_ok(&[
        "synth",
        "-o",
        &path("seq"),
        "--frames",
        "60",
        "--laps",
        "3",
        "--rate",
        "1",
        "--width",
        "160",
        "--height",
        "120",
        "--seed",
        "5",
    ]);
    let out = path("place.safetensors");
    support::ecm_lcd_ok(&[
        "--threads",
        "2",
        "train-place",
        &path("seq"),
        "--param",
        "arch=ecmobilenet",
        "--size",
        "64",
        "--epochs",
        "4",
        "--batch",
        "4",
        "--lr",
        "1e-3",
        "--min-gap",
        "10",
        "--quiet",
        "-o",
        &out,
    ]);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(path("place.json")).unwrap()).unwrap();
    let losses: Vec<f64> = report["epoch_loss"].as_array().unwrap().iter().map(|l| l.as_f64().unwrap()).collect();
    assert_eq!(losses.len(), 4);
    let anchors = report["anchors"].as_u64().unwrap();
    // Laps of 20 s at 1 Hz: every frame of a lap has a revisit 20 s away in another lap.
    assert!(anchors >= 40, "{anchors} anchors");
    assert_eq!(report["steps"].as_u64().unwrap(), 4 * (anchors / 4));
    assert!(losses[3] < losses[0], "the triplet loss did not fall: {losses:?}");
    assert_eq!(report["config"]["descriptor"], "regional-3x3-mac");

    let replay =
        support::ecm_lcd_ok(&["replay", &path("seq"), "--weights", &out, "--param", "arch=ecmobilenet", "--quiet"]);
    assert!(String::from_utf8_lossy(&replay.stdout).starts_with("query_id,"));
}
