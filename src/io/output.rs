//! Files a command writes: an output is never one of the command's own inputs, a file its source
//! folders hold, or another of its outputs, and a whole-file output replaces a regular file only by
//! rename.
//!
//! The input check runs before anything is read or written, so a mistyped `-o` that names an input
//! (`embed img.jpg -o img.jpg`, `db export k.db -o k.db`) leaves every file as it was.

use std::io::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

/// Creates the folder `path` is to be written in, where it does not exist: an output may name a new
/// folder (`-o results/run1.csv`).
pub fn create_folder_of(path: &Path) -> Result<()> {
    match path.parent().filter(|dir| !dir.as_os_str().is_empty()) {
        Some(dir) => std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display())),
        None => Ok(()),
    }
}

/// Writes `bytes` as the whole of `path` ([`replace_with`]).
pub fn write_replacing(path: &Path, bytes: &[u8]) -> Result<()> {
    replace_with(path, |out| Ok(out.write_all(bytes)?))
}

/// Writes the whole of `path` with `write`. A missing path or a regular file is written under a
/// temporary name beside it and renamed over it, so a crash or an error leaves the old file or the new
/// one, never half of one. A symlink, FIFO or device is written in place (through the link, into the
/// pipe); a directory is refused.
pub fn replace_with(path: &Path, write: impl FnOnce(&mut dyn std::io::Write) -> Result<()>) -> Result<()> {
    let in_place = match std::fs::symlink_metadata(path) {
        Err(_) => false,
        Ok(m) if m.is_dir() => bail!("cannot write {}: it is a directory", path.display()),
        Ok(m) => !m.file_type().is_file(),
    };
    if in_place {
        let file = std::fs::OpenOptions::new()
            .write(true)
            .truncate(true)
            .open(path)
            .with_context(|| format!("cannot open {} for writing", path.display()))?;
        let mut out = std::io::BufWriter::new(file);
        write(&mut out).and_then(|()| Ok(out.flush()?)).with_context(|| format!("cannot write {}", path.display()))?;
        return Ok(());
    }
    let name = path.file_name().with_context(|| format!("cannot write {}: not a file name", path.display()))?;
    let temporary = path.with_file_name(format!(".{}.{}.tmp", name.to_string_lossy(), std::process::id()));
    let written = (|| -> Result<()> {
        let file = std::fs::File::create(&temporary)?;
        let mut out = std::io::BufWriter::new(file);
        write(&mut out)?;
        out.into_inner().map_err(|e| e.into_error())?.sync_all()?;
        std::fs::rename(&temporary, path)?;
        Ok(())
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_file(&temporary);
        return Err(e).with_context(|| format!("cannot write {}", path.display()));
    }
    Ok(())
}

/// Refuses an image output whose name does not end in `.png` (the one format plots are written in),
/// before any work is done.
pub fn ensure_png(path: &Path, flag: &str) -> Result<()> {
    if !path.extension().is_some_and(|e| e.eq_ignore_ascii_case("png")) {
        bail!("{flag} {}: plots are written as PNG; give a file name ending in .png", path.display());
    }
    Ok(())
}

/// Whether `a` and `b` name the same existing file (hard links and symlinks included).
pub fn same_file(a: &Path, b: &Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        if let (Ok(x), Ok(y)) = (std::fs::metadata(a), std::fs::metadata(b)) {
            return x.dev() == y.dev() && x.ino() == y.ino();
        }
    }
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(x), Ok(y)) => x == y,
        _ => false,
    }
}

/// `path` made absolute without its needing to exist: resolved itself where it exists, else its
/// folder resolved and its name joined (`None` where neither can be).
fn resolved(path: &Path) -> Option<PathBuf> {
    if let Ok(absolute) = path.canonicalize() {
        return Some(absolute);
    }
    let folder = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    Some(folder.canonicalize().ok()?.join(path.file_name()?))
}

/// Makes each output's folder and refuses outputs (each with its flag) that could not all be
/// written, before any work, so that a command does not write some and then fail on the next: one
/// whose folder cannot be made, one that is a folder, or two that name one file, existing or not
/// (the second one written would replace the first).
pub fn ensure_writable_outputs(outputs: &[(&str, &Path)]) -> Result<()> {
    for &(flag, path) in outputs {
        create_folder_of(path).with_context(|| format!("{flag} {}", path.display()))?;
        if path.is_dir() {
            bail!("{flag} {} is a folder, not a regular file; give a file name", path.display());
        }
    }
    for (i, &(flag, path)) in outputs.iter().enumerate() {
        for &(other_flag, other) in &outputs[i + 1..] {
            let same = same_file(path, other) || resolved(path).is_some_and(|p| resolved(other) == Some(p));
            if same {
                bail!("{flag} and {other_flag} both name {}; each output needs its own file", path.display());
            }
        }
    }
    Ok(())
}

/// Every check a command's outputs need before it reads anything: none may be one of the `inputs`
/// (the `sources` among them), a file a source folder reads ([`ensure_not_in_source`]), or another
/// output; the keyframe database `database` (`--db`), which is read and written, is none of the
/// inputs, and no other output is it or one of its files beside it.
pub fn ensure_outputs(
    sources: &[&Path],
    inputs: &[&Path],
    database: Option<&Path>,
    outputs: &[(&str, &Path)],
) -> Result<()> {
    let mut read: Vec<&Path> = sources.iter().chain(inputs).copied().collect();
    if let Some(database) = database {
        ensure_not_an_input(database, &read)?;
        ensure_not_in_source(database, sources)?;
    }
    read.extend(database);
    for &(_, output) in outputs {
        ensure_not_an_input(output, &read)?;
        if let Some(database) = database {
            ensure_not_beside_database(output, database)?;
        }
        ensure_not_in_source(output, sources)?;
    }
    let all: Vec<(&str, &Path)> = database.map(|db| ("--db", db)).into_iter().chain(outputs.iter().copied()).collect();
    ensure_writable_outputs(&all)
}

/// The text files of a TUM folder (the benchmark's, and `odometry.txt` from `synth`).
const TUM_FILES: [&str; 5] = ["rgb.txt", "depth.txt", "groundtruth.txt", "accelerometer.txt", "odometry.txt"];

/// Refuses `output` where it would change what one of the `sources` that are folders reads:
/// - an existing image, or a TUM folder's lists (`rgb.txt`, ...), anywhere inside one;
/// - a ROS 2 bag folder's `metadata.yaml` and storage files (`.db3`, `.mcap`, compressed `.zstd`);
/// - an image name directly inside an image folder, even a new one: it would be read as a frame
///   the next time, and every later frame's index would shift.
///
/// Both where the output is and, for a symlink, where it leads are checked (writing follows the
/// link). Other files there (a CSV written before, a keyframe database) may be replaced.
pub fn ensure_not_in_source(output: &Path, sources: &[&Path]) -> Result<()> {
    let is_image = crate::io::tum::has_image_extension(output);
    let is_tum_list = output.file_name().and_then(|n| n.to_str()).is_some_and(|n| TUM_FILES.contains(&n));
    let exists = output.is_file();
    let name = output.file_name().and_then(|n| n.to_str()).unwrap_or_default();
    let is_bag_file = name == "metadata.yaml"
        || Path::new(name).extension().and_then(|e| e.to_str()).is_some_and(|e| ["db3", "mcap", "zstd"].contains(&e));
    // Where the output is named (its folder resolved, its own name kept), and where it leads.
    let folder = output.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let named = folder.canonicalize().ok().zip(output.file_name()).map(|(folder, name)| folder.join(name));
    let places: Vec<PathBuf> = named.into_iter().chain(output.canonicalize().ok()).collect();
    for source in sources.iter().filter(|s| s.is_dir()) {
        let Ok(folder) = source.canonicalize() else { continue };
        let read_by_source = places.iter().filter(|place| place.starts_with(&folder)).any(|place| {
            (exists && (is_image || is_tum_list))
                || (exists && is_bag_file && folder.join("metadata.yaml").is_file())
                || (is_image && crate::io::is_image_folder(&folder) && place.parent() == Some(folder.as_path()))
        });
        if read_by_source {
            bail!(
                "the output {} is a file of the source folder {}; writing it would change the source (choose another output path)",
                output.display(),
                source.display()
            );
        }
    }
    Ok(())
}

/// Refuses `output` when it is the same file as one of `inputs` (an input that does not exist yet,
/// or an output that does not, never clashes: [`ensure_writable_outputs`] checks outputs).
/// A keyframe database's files beside it (its write-ahead log, shared memory and vector file) count
/// as the input too ([`ensure_not_beside_database`]), where the database is there.
pub fn ensure_not_an_input(output: &Path, inputs: &[&Path]) -> Result<()> {
    if let Some(input) = inputs.iter().find(|input| same_file(output, input)) {
        bail!(
            "the output {} is the input {}; writing it would destroy the input (choose another output path)",
            output.display(),
            input.display()
        );
    }
    for input in inputs.iter().filter(|input| crate::detector::store::is_keyframe_store(input)) {
        ensure_not_beside_database(output, input)?;
    }
    Ok(())
}

/// A path beside `path` named for `what` and this process, with no file there (nor beside it as a
/// store's `-wal`, `-shm`, `-vectors`): a temporary name only this writer uses, so that cleaning up
/// removes nothing it did not make.
pub fn unused_name_beside(path: &Path, what: &str) -> Result<PathBuf> {
    for attempt in 0..100u32 {
        let mut name = path.as_os_str().to_owned();
        name.push(format!(".{what}-{}-{attempt}", std::process::id()));
        let name = PathBuf::from(name);
        let taken = ["", "-wal", "-shm", "-vectors", ".creating"].iter().any(|suffix| {
            let mut beside = name.as_os_str().to_owned();
            beside.push(suffix);
            std::fs::symlink_metadata(PathBuf::from(beside)).is_ok()
        });
        if !taken {
            return Ok(name);
        }
    }
    bail!("no unused temporary name beside {}", path.display())
}

/// Refuses an `output` that is one of the files SQLite and the vector file keep beside the keyframe
/// database `database` (`<db>-wal`, ...), whether the database or the file is there yet or not.
pub fn ensure_not_beside_database(output: &Path, database: &Path) -> Result<()> {
    for suffix in crate::detector::store::FILES_BESIDE {
        let mut beside = database.as_os_str().to_owned();
        beside.push(suffix);
        let beside = PathBuf::from(beside);
        if same_file(output, &beside) || resolved(output).is_some_and(|o| resolved(&beside) == Some(o)) {
            bail!(
                "the output {} is the keyframe database {}'s own {suffix} file; writing it would damage the \
                 database (choose another output path)",
                output.display(),
                database.display()
            );
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_output_that_a_source_folder_would_read_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = |name: &str| dir.path().join(name);
        for folder in ["bag", "images/sub", "tum/rgb"] {
            std::fs::create_dir_all(path(folder)).unwrap();
        }
        for file in ["bag/metadata.yaml", "bag/bag_0.mcap", "images/0.png", "tum/rgb.txt", "tum/rgb/0.png", "old.csv"] {
            std::fs::write(path(file), b"x").unwrap();
        }
        let sources = [path("bag"), path("images"), path("tum")];
        let sources: Vec<&Path> = sources.iter().map(PathBuf::as_path).collect();
        let refused = |name: &str| ensure_not_in_source(&path(name), &sources).is_err();
        // A bag folder's files, the images and lists a folder reads, and a new image an image
        // folder would read as a frame.
        for name in
            ["bag/bag_0.mcap", "bag/metadata.yaml", "images/0.png", "images/new.PNG", "tum/rgb.txt", "tum/rgb/0.png"]
        {
            assert!(refused(name), "{name} allowed");
        }
        // New files no source reads, files outside the sources, and a bag folder's other files,
        // existing or not (a keyframe database kept there is written again on every run).
        std::fs::write(path("bag/k.db"), b"x").unwrap();
        for name in [
            "bag/new.csv",
            "bag/k.db",
            "images/new.csv",
            "images/sub/new.png",
            "tum/rgb/new.png",
            "tum/new.png",
            "old.csv",
        ] {
            assert!(!refused(name), "{name} refused");
        }
        // A symlink in a source folder to a file elsewhere, and one elsewhere to a source's file:
        // writing follows the link.
        #[cfg(unix)]
        {
            std::os::unix::fs::symlink(path("old.csv"), path("images/linked.png")).unwrap();
            std::os::unix::fs::symlink(path("images/0.png"), path("outside.png")).unwrap();
            assert!(refused("images/linked.png"));
            assert!(refused("outside.png"));
        }
    }

    #[test]
    fn a_keyframe_databases_files_beside_it_are_inputs_too() {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join("k.db");
        rusqlite::Connection::open(&db).unwrap().execute_batch("CREATE TABLE t (x)").unwrap();
        for beside in ["k.db-wal", "k.db-shm", "k.db-vectors"] {
            let err = ensure_not_an_input(&dir.path().join(beside), &[&db]).unwrap_err().to_string();
            assert!(err.contains("k.db's own") && err.contains(&beside[4..]), "{err}");
        }
        ensure_not_an_input(&dir.path().join("k.db-export.csv"), &[&db]).unwrap();
        // Beside a file that is not a keyframe database, such names are free.
        let text = dir.path().join("notes.txt");
        std::fs::write(&text, "x").unwrap();
        ensure_not_an_input(&dir.path().join("notes.txt-wal"), &[&text]).unwrap();
        // A --db not made yet has them too.
        let new = dir.path().join("new.db");
        let err = ensure_not_beside_database(&dir.path().join("new.db-wal"), &new).unwrap_err().to_string();
        assert!(err.contains("new.db's own -wal file"), "{err}");
        // A temporary name beside a path is free, and another than one taken.
        let taken = unused_name_beside(&db, "merging").unwrap();
        assert!(!taken.exists() && taken.to_string_lossy().contains("k.db.merging-"));
        std::fs::write(&taken, "x").unwrap();
        assert_ne!(unused_name_beside(&db, "merging").unwrap(), taken);
    }

    #[test]
    fn whole_file_outputs_replace_regular_files_and_write_through_everything_else() {
        let dir = tempfile::tempdir().unwrap();
        let fresh = dir.path().join("new.txt");
        write_replacing(&fresh, b"one").unwrap();
        assert_eq!(std::fs::read(&fresh).unwrap(), b"one");
        write_replacing(&fresh, b"two").unwrap();
        assert_eq!(std::fs::read(&fresh).unwrap(), b"two");
        // Nothing but the output is left in the folder.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        let err = write_replacing(dir.path(), b"x").unwrap_err().to_string();
        assert!(err.contains("directory"), "{err}");
        #[cfg(unix)]
        {
            let target = dir.path().join("target.txt");
            std::fs::write(&target, b"old").unwrap();
            let link = dir.path().join("link.txt");
            std::os::unix::fs::symlink(&target, &link).unwrap();
            write_replacing(&link, b"through").unwrap();
            assert!(std::fs::symlink_metadata(&link).unwrap().file_type().is_symlink(), "the link stays a link");
            assert_eq!(std::fs::read(&target).unwrap(), b"through");
            write_replacing(Path::new("/dev/null"), b"gone").unwrap();
            assert!(!std::fs::metadata("/dev/null").unwrap().is_file(), "/dev/null stays a device");
        }
    }

    #[test]
    fn an_input_is_refused_as_the_output_by_any_name() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("in.jpg");
        std::fs::write(&input, b"image").unwrap();
        let other = dir.path().join("out.csv");
        assert!(ensure_not_an_input(&other, &[&input]).is_ok());
        let err = ensure_not_an_input(&input, &[&other, &input]).unwrap_err().to_string();
        assert!(err.contains("in.jpg") && err.contains("destroy"), "{err}");
        // Another spelling, a symlink and a hard link are the same file.
        let spelled = dir.path().join(".").join("in.jpg");
        assert!(ensure_not_an_input(&spelled, &[&input]).is_err());
        #[cfg(unix)]
        {
            let link = dir.path().join("link.jpg");
            std::os::unix::fs::symlink(&input, &link).unwrap();
            assert!(ensure_not_an_input(&link, &[&input]).is_err());
            let hard = dir.path().join("hard.jpg");
            std::fs::hard_link(&input, &hard).unwrap();
            assert!(ensure_not_an_input(&hard, &[&input]).is_err());
        }
        assert_eq!(std::fs::read(&input).unwrap(), b"image");
    }
}
