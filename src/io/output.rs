//! Output files and folders: nothing the user had is overwritten without being asked, and every
//! refusal comes before any work, so that it costs nothing.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

/// An error if `path` exists and `overwrite` (--force) was not given.
pub fn refuse_overwrite(path: &Path, overwrite: bool) -> Result<()> {
    if path.exists() && !overwrite {
        bail!(
            "'{}' already exists: pass --force to overwrite it",
            path.display()
        );
    }
    Ok(())
}

/// Creates `out` and refuses, before any work, to overwrite one of `files` without `overwrite`.
pub fn prepare_out_dir(out: &Path, files: &[PathBuf], overwrite: bool) -> Result<()> {
    for f in files {
        refuse_overwrite(f, overwrite)?;
    }
    std::fs::create_dir_all(out)
        .with_context(|| format!("cannot create the output directory '{}'", out.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn existing_files_are_kept_unless_forced() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a.csv");
        std::fs::write(&file, "mine").unwrap();
        let out = dir.path().join("new");
        let err = prepare_out_dir(&out, &[file.clone(), out.join("b.csv")], false).unwrap_err();
        assert!(err.to_string().contains("--force"), "{err}");
        assert!(!out.exists(), "refused before creating anything");
        prepare_out_dir(&out, std::slice::from_ref(&file), true).unwrap();
        assert!(out.is_dir());
        assert_eq!(std::fs::read_to_string(&file).unwrap(), "mine");
    }
}
