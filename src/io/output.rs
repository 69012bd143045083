//! Guards for files a command writes: an output is never one of the command's own inputs.
//!
//! Checked before anything is read or written, so a mistyped `-o` that names an input (`embed
//! img.jpg -o img.jpg`, `db export k.db -o k.db`) leaves every file as it was.

use std::path::Path;

use anyhow::{bail, Result};

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

/// Refuses `output` when it is the same file as one of `inputs` (an input that does not exist yet,
/// or an output that does not, never clashes).
pub fn ensure_not_an_input(output: &Path, inputs: &[&Path]) -> Result<()> {
    if let Some(input) = inputs.iter().find(|input| same_file(output, input)) {
        bail!(
            "the output {} is the input {}; writing it would destroy the input (choose another output path)",
            output.display(),
            input.display()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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
