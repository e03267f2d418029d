//! Output files and folders: nothing the user had is overwritten without being asked, and every
//! refusal comes before any work, so that it costs nothing.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

/// An error if `path` exists and `overwrite` (--force) was not given, or is a folder (which
/// --force does not replace). Checked for every output before the first is written, so that a
/// command that fails on one leaves none.
pub fn refuse_overwrite(path: &Path, overwrite: bool) -> Result<()> {
    if path.is_dir() {
        bail!("cannot write '{}': it is a folder", path.display());
    }
    // `symlink_metadata`: a link to a file not yet there is the user's too (`exists` follows it).
    if path.symlink_metadata().is_ok() && !overwrite {
        bail!(
            "'{}' already exists: pass --force to overwrite it",
            path.display()
        );
    }
    Ok(())
}

/// An error unless `path`, given as `--output`, names a file ending in `.{ext}`. A bare `.exr` is a
/// hidden file without an extension to the file system: it is told so, not that it "must end in
/// .exr".
pub fn require_extension(path: &Path, ext: &str) -> Result<()> {
    if path.extension().and_then(|e| e.to_str()) == Some(ext) {
        return Ok(());
    }
    if path.file_name().and_then(|n| n.to_str()) == Some(&format!(".{ext}")) {
        bail!(
            "--output '{}' has no name before its .{ext}",
            path.display()
        );
    }
    bail!("--output must end in .{ext} (got '{}')", path.display())
}

/// An error unless `path`'s folder exists and a file can be made in it: checked before the work
/// that fills `path`, which would otherwise end, after a render of hours, at "the folder does not
/// exist". (A probe file is made and removed: permission bits do not say what root, ACLs or a
/// read-only mount allow.)
pub fn refuse_unwritable_folder(path: &Path) -> Result<()> {
    let folder = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if !folder.is_dir() {
        bail!(
            "cannot write '{}': the folder '{}' does not exist",
            path.display(),
            folder.display()
        );
    }
    let probe = folder.join(format!(".volgrad-write-check-{}", std::process::id()));
    match std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
    {
        Ok(_) => {
            let _ = std::fs::remove_file(&probe);
            Ok(())
        }
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(()),
        Err(e) => bail!(
            "cannot write '{}': the folder '{}' does not take new files ({e})",
            path.display(),
            folder.display()
        ),
    }
}

/// Creates `out` and refuses, before any work, to overwrite one of `files` without `overwrite`.
pub fn prepare_out_dir(out: &Path, files: &[PathBuf], overwrite: bool) -> Result<()> {
    for f in files {
        refuse_overwrite(f, overwrite)?;
    }
    std::fs::create_dir_all(out)
        .with_context(|| format!("cannot create the output directory '{}'", out.display()))
}

/// Writes `path` whole: `write` fills a temporary file beside it, which is then renamed over
/// `path`, so that a process killed mid-write leaves the old file (or none), never half of one.
pub fn write_whole(
    path: &Path,
    write: impl FnOnce(&mut std::io::BufWriter<std::fs::File>) -> std::io::Result<()>,
) -> Result<()> {
    let name = path
        .file_name()
        .map_or("out".into(), |n| n.to_string_lossy());
    let temporary = path.with_file_name(format!(".{name}.{}.tmp", std::process::id()));
    let written = std::fs::File::create(&temporary).and_then(|file| {
        let mut w = std::io::BufWriter::new(file);
        write(&mut w)?;
        w.into_inner().map_err(|e| e.into_error())?.sync_all()
    });
    let renamed = written.and_then(|()| std::fs::rename(&temporary, path));
    if renamed.is_err() {
        let _ = std::fs::remove_file(&temporary);
    }
    renamed.with_context(|| format!("writing '{}'", path.display()))
}

/// `write_whole` of a text or bytes.
pub fn write_bytes_whole(path: &Path, bytes: impl AsRef<[u8]>) -> Result<()> {
    write_whole(path, |w| std::io::Write::write_all(w, bytes.as_ref()))
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

    #[test]
    fn an_output_names_its_kind_after_a_name() {
        let message = |path: &str| match require_extension(Path::new(path), "exr") {
            Ok(()) => String::from("ok"),
            Err(e) => e.to_string(),
        };
        assert_eq!(message("out/a.exr"), "ok");
        assert!(message("a.png").contains("must end in .exr (got 'a.png')"));
        assert!(message(".exr").contains("'.exr' has no name before its .exr"));
        assert!(message("out/.exr").contains("has no name before its .exr"));
    }

    /// A write that fails half-way leaves the old file as it was and no temporary beside it.
    #[test]
    fn a_failed_write_leaves_the_old_file() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("state");
        write_bytes_whole(&file, "old").unwrap();
        let failed = write_whole(&file, |w| {
            std::io::Write::write_all(w, b"half")?;
            Err(std::io::Error::other("disk full"))
        });
        assert!(failed.unwrap_err().to_string().contains("state"));
        assert_eq!(std::fs::read_to_string(&file).unwrap(), "old");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        write_bytes_whole(&file, "new").unwrap();
        assert_eq!(std::fs::read_to_string(&file).unwrap(), "new");
    }
}
