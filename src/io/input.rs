//! Input files: only a regular file (or a link to one) is read. A FIFO or a device named as an
//! input would otherwise be read until something writes to it, which may be never; the VDB and
//! image readers refuse them the same way (`cpp/files.cpp`).

use std::fs::File;
use std::path::Path;

use anyhow::{bail, Result};

/// `path` opened for reading, after checking that it is a regular file. A missing file keeps its
/// `std::io::Error` (NotFound) in the error's chain.
pub fn open_regular(path: &Path) -> Result<File> {
    let metadata = std::fs::metadata(path)?;
    if !metadata.is_file() {
        bail!("'{}' is not a regular file", path.display());
    }
    Ok(File::open(path)?)
}

/// The text of the regular file `path`, without the byte-order mark some Windows tools write
/// first (JSON and COLMAP's readers would take it for the first character of the data).
pub fn read_text(path: &Path) -> Result<String> {
    let mut text = String::new();
    std::io::Read::read_to_string(&mut open_regular(path)?, &mut text)?;
    if text.starts_with('\u{feff}') {
        text.drain(..'\u{feff}'.len_utf8());
    }
    Ok(text)
}

/// The bytes of the regular file `path`.
pub fn read_bytes(path: &Path) -> Result<Vec<u8>> {
    let mut bytes = Vec::new();
    std::io::Read::read_to_end(&mut open_regular(path)?, &mut bytes)?;
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_fifo_is_refused_without_blocking() {
        let dir = std::env::temp_dir().join(format!("volgrad-input-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let fifo = dir.join("scene.toml");
        let made = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap();
        assert!(made.success());
        let error = read_text(&fifo).unwrap_err().to_string();
        assert!(error.contains("not a regular file"), "{error}");
        let missing = read_text(&dir.join("none.toml")).unwrap_err();
        let kind = missing.downcast_ref::<std::io::Error>().map(|e| e.kind());
        assert_eq!(kind, Some(std::io::ErrorKind::NotFound));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_byte_order_mark_is_not_read_as_text() {
        let file = tempfile::NamedTempFile::new().unwrap();
        std::fs::write(
            file.path(),
            "\u{feff}# Camera list\n1 PINHOLE 8 8 9 9 4 4\n",
        )
        .unwrap();
        assert_eq!(
            read_text(file.path()).unwrap(),
            "# Camera list\n1 PINHOLE 8 8 9 9 4 4\n"
        );
        // Only a first one: one inside the text is the text's.
        std::fs::write(file.path(), "a\u{feff}").unwrap();
        assert_eq!(read_text(file.path()).unwrap(), "a\u{feff}");
    }
}
