//! Atomic output: every writer goes through [`write_atomic`], which writes a temporary file
//! beside the target and renames it into place only after the content is complete and synced.
//! A failure (an error, a panic, a full disk) never leaves a partial or clobbered file.
//! The file gets the permissions a plain write gives (0666 less the umask), not the private
//! 0600 of a temporary file.

use std::io::{BufWriter, Write};
use std::path::Path;

use crate::error::{Error, Result};

/// Writes `path` atomically: `fill` writes the whole content into the given writer.
pub fn write_atomic<F>(path: &Path, fill: F) -> Result<()>
where
    F: FnOnce(&mut dyn Write) -> Result<()>,
{
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let mut builder = tempfile::Builder::new();
    builder.prefix(".doefab-").suffix(".partial");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        // Applied at creation, so the umask restricts it as it does any write.
        builder.permissions(std::fs::Permissions::from_mode(0o666));
    }
    let tmp = builder.tempfile_in(dir).map_err(|e| Error::io(dir, e))?;
    {
        let mut w = BufWriter::new(tmp.as_file());
        fill(&mut w)?;
        w.flush().map_err(|e| Error::io(path, e))?;
    }
    tmp.as_file().sync_all().map_err(|e| Error::io(path, e))?;
    tmp.persist(path).map_err(|e| Error::io(path, e.error))?;
    Ok(())
}

/// Writes a byte buffer atomically.
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic(path, |w| w.write_all(bytes).map_err(|e| Error::io(path, e)))
}

/// Writes pretty JSON atomically (with a trailing newline).
pub fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<()> {
    let mut text = serde_json::to_string_pretty(value)
        .map_err(|e| Error::encoding(path, format!("cannot serialise JSON: {e}")))?;
    text.push('\n');
    write_bytes(path, text.as_bytes())
}

/// A folder of outputs that appears all at once: files are written into a hidden staging
/// folder beside the destination and moved in by [`StagedDir::commit`]. Dropping it without
/// committing (an error half way) deletes the staging folder, so a failed run leaves nothing
/// in the destination; files from an earlier run there are replaced only on success.
pub struct StagedDir {
    stage: tempfile::TempDir,
    dest: std::path::PathBuf,
    names: Vec<String>,
}

impl StagedDir {
    /// Prepares staging for the destination folder `dest`.
    pub fn new(dest: &Path) -> Result<StagedDir> {
        let parent = match dest.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
        let stage = tempfile::Builder::new()
            .prefix(".doefab-stage-")
            .tempdir_in(parent)
            .map_err(|e| Error::io(parent, e))?;
        Ok(StagedDir { stage, dest: dest.to_path_buf(), names: Vec::new() })
    }

    /// Where to write the file `name` now (inside the staging folder).
    pub fn stage_path(&mut self, name: &str) -> std::path::PathBuf {
        if !self.names.iter().any(|n| n == name) {
            self.names.push(name.to_string());
        }
        self.stage.path().join(name)
    }

    /// Where the file `name` will be after [`commit`](Self::commit).
    pub fn final_path(&self, name: &str) -> std::path::PathBuf {
        self.dest.join(name)
    }

    /// Moves every staged file into the destination (each move is a rename).
    pub fn commit(self) -> Result<()> {
        std::fs::create_dir_all(&self.dest).map_err(|e| Error::io(&self.dest, e))?;
        for n in &self.names {
            let from = self.stage.path().join(n);
            if from.exists() {
                let to = self.dest.join(n);
                std::fs::rename(&from, &to).map_err(|e| Error::io(&to, e))?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failing_writer_leaves_the_old_file_and_no_debris() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("out.txt");
        write_bytes(&p, b"old").unwrap();
        let r = write_atomic(&p, |w| {
            w.write_all(b"partial new content").unwrap();
            Err(Error::internal("boom"))
        });
        assert!(r.is_err());
        assert_eq!(std::fs::read(&p).unwrap(), b"old");
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names.len(), 1, "left behind: {names:?}");
        write_bytes(&p, b"new").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"new");
    }

    #[cfg(unix)]
    #[test]
    fn outputs_get_the_permissions_of_a_plain_write() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let plain = dir.path().join("plain.txt");
        std::fs::write(&plain, b"x").unwrap();
        let ours = dir.path().join("ours.txt");
        write_bytes(&ours, b"x").unwrap();
        let mut staged = StagedDir::new(&dir.path().join("out")).unwrap();
        write_bytes(&staged.stage_path("s.txt"), b"x").unwrap();
        staged.commit().unwrap();
        let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode(&ours), mode(&plain));
        assert_eq!(mode(&dir.path().join("out/s.txt")), mode(&plain));
    }

    #[test]
    fn a_staged_folder_appears_only_on_commit() {
        let dir = tempfile::tempdir().unwrap();
        let dest = dir.path().join("out");
        {
            let mut s = StagedDir::new(&dest).unwrap();
            write_bytes(&s.stage_path("a.txt"), b"a").unwrap();
            // Dropped without commit: as if a later step had failed.
        }
        assert!(!dest.exists());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0, "staging folder left behind");
        let mut s = StagedDir::new(&dest).unwrap();
        write_bytes(&s.stage_path("a.txt"), b"a").unwrap();
        assert_eq!(s.final_path("a.txt"), dest.join("a.txt"));
        s.commit().unwrap();
        assert_eq!(std::fs::read(dest.join("a.txt")).unwrap(), b"a");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}
