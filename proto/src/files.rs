//! Files an operator names (tokens, certificates, maps, experiment configs),
//! read whole but only up to a limit: a mistaken path (`/dev/zero`, a FIFO,
//! a map's image instead of its YAML) then fails with a message instead of
//! filling the memory or never returning.

use std::io::{self, Read};
use std::path::Path;

/// A mebibyte, the unit the limits are given in.
pub const MIB: u64 = 1 << 20;

/// The file's bytes, or `FileTooLarge` if it holds more than `limit_mib`
/// mebibytes.
pub fn read_at_most(path: &Path, limit_mib: u64) -> io::Result<Vec<u8>> {
    let limit = limit_mib * MIB;
    let mut bytes = Vec::new();
    std::fs::File::open(path)?.take(limit + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > limit {
        let message = format!("larger than {limit_mib} MiB, far more than such a file holds: is it the right file?");
        return Err(io::Error::new(io::ErrorKind::FileTooLarge, message));
    }
    Ok(bytes)
}

/// A PEM file (certificate, key, CA) of at most 1 MiB; its errors name it
/// ("cert.pem: No such file or directory"), as the caller reads several.
pub fn read_pem(path: &Path) -> io::Result<Vec<u8>> {
    read_at_most(path, 1).map_err(|e| io::Error::new(e.kind(), format!("{}: {e}", path.display())))
}

/// [`read_at_most`] for a text file; `InvalidData` if it is not UTF-8.
pub fn read_text_at_most(path: &Path, limit_mib: u64) -> io::Result<String> {
    String::from_utf8(read_at_most(path, limit_mib)?).map_err(|e| {
        io::Error::new(io::ErrorKind::InvalidData, format!("not UTF-8 text (byte {})", e.utf8_error().valid_up_to()))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_within_the_limit_is_read_and_one_beyond_it_or_endless_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let (exact, over) = (dir.path().join("exact"), dir.path().join("over"));
        std::fs::write(&exact, vec![b'a'; MIB as usize]).unwrap();
        std::fs::write(&over, vec![b'a'; MIB as usize + 1]).unwrap();
        assert_eq!(read_text_at_most(&exact, 1).unwrap().len(), MIB as usize);
        assert_eq!(read_at_most(&over, 1).unwrap_err().kind(), io::ErrorKind::FileTooLarge);
        assert_eq!(read_at_most(Path::new("/dev/zero"), 1).unwrap_err().kind(), io::ErrorKind::FileTooLarge);
        std::fs::write(&exact, [b'a', 0xff]).unwrap();
        assert!(read_text_at_most(&exact, 1).unwrap_err().to_string().contains("byte 1"));
    }
}
