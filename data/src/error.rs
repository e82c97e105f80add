//! One error type for the data crate.
//!
//! Bad data must produce one line that a user can act on: *which* subject, *which* frame, *which*
//! field, and what is wrong with it. Every variant therefore carries a [`Location`] (file,
//! subject, frame, field, each optional) next to the reason. Nothing in this crate panics on bad
//! input.

use std::fmt;
use std::path::PathBuf;

/// Where a problem is: as much of file / subject / frame / field as is known.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Location {
    /// The file read (a pickle, a PNG, a split JSON, a config).
    pub file: Option<PathBuf>,
    /// The subject (scene) folder name.
    pub subject: Option<String>,
    /// The frame name (`frame_000012`).
    pub frame: Option<String>,
    /// The field (`cameras.pkl[frame]['extrinsics']`, `canonical_joints.pkl['weights']`, ...).
    pub field: Option<String>,
}

impl Location {
    /// A location naming only a file.
    pub fn file(path: impl Into<PathBuf>) -> Self {
        Self {
            file: Some(path.into()),
            ..Self::default()
        }
    }

    /// The same location with `subject` set.
    pub fn subject(mut self, subject: impl Into<String>) -> Self {
        self.subject = Some(subject.into());
        self
    }

    /// The same location with `frame` set.
    pub fn frame(mut self, frame: impl Into<String>) -> Self {
        self.frame = Some(frame.into());
        self
    }

    /// The same location with `field` set.
    pub fn field(mut self, field: impl Into<String>) -> Self {
        self.field = Some(field.into());
        self
    }
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut parts = Vec::new();
        if let Some(s) = &self.subject {
            parts.push(format!("subject `{s}`"));
        }
        if let Some(s) = &self.frame {
            parts.push(format!("frame `{s}`"));
        }
        if let Some(s) = &self.field {
            parts.push(format!("field `{s}`"));
        }
        if let Some(p) = &self.file {
            parts.push(format!("file {}", p.display()));
        }
        if parts.is_empty() {
            f.write_str("(no location)")
        } else {
            f.write_str(&parts.join(", "))
        }
    }
}

/// Errors raised by the data crate. Locations are boxed to keep `Result`s small.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// A file that does not exist or cannot be read.
    #[error("{location}: cannot read: {source}")]
    Io {
        /// What was being read.
        location: Box<Location>,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A file that cannot be written (a full disk, a read-only folder); the previous file, if
    /// any, is left whole (writes go through a temporary and a rename).
    #[error("{location}: cannot write: {source}")]
    Write {
        /// What was being written.
        location: Box<Location>,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A pickle stream the VM cannot execute (truncated, unknown opcode, unknown global, ...).
    #[error("{location}: pickle error at byte {offset}: {reason}")]
    Pickle {
        /// The pickle file.
        location: Box<Location>,
        /// Byte offset of the opcode at fault.
        offset: usize,
        /// What is wrong.
        reason: String,
    },
    /// A value of the wrong type, shape or dtype, a missing key, a NaN, a wrong joint count, ...
    #[error("{location}: {reason}")]
    Invalid {
        /// Where.
        location: Box<Location>,
        /// What is wrong with it.
        reason: String,
    },
    /// An unreadable or inconsistent image (PNG decode failure, image/mask size mismatch).
    #[error("{location}: image: {reason}")]
    Image {
        /// Where.
        location: Box<Location>,
        /// What is wrong with it.
        reason: String,
    },
    /// A config file that does not parse or holds an impossible setting.
    #[error("config {location}: {reason}")]
    Config {
        /// The config file (and the key, as `field`).
        location: Box<Location>,
        /// What is wrong.
        reason: String,
    },
    /// A geometry error from the render crate (template, camera, skeleton), with its context.
    #[error("{location}: {source}")]
    Render {
        /// Where.
        location: Box<Location>,
        /// The render crate's error.
        source: lifegom_render::RenderError,
    },
}

impl DataError {
    /// A [`DataError::Invalid`] at `location`.
    pub fn invalid(location: Location, reason: impl Into<String>) -> Self {
        Self::Invalid {
            location: Box::new(location),
            reason: reason.into(),
        }
    }

    /// A [`DataError::Io`] for `path`.
    pub fn io(location: Location, source: std::io::Error) -> Self {
        Self::Io {
            location: Box::new(location),
            source,
        }
    }

    /// A [`DataError::Write`] for `location`.
    pub fn write(location: Location, source: std::io::Error) -> Self {
        Self::Write {
            location: Box::new(location),
            source,
        }
    }

    /// A [`DataError::Render`] at `location`.
    pub fn render(location: Location, source: lifegom_render::RenderError) -> Self {
        Self::Render {
            location: Box::new(location),
            source,
        }
    }
}

/// Result alias for the data crate.
pub type Result<T, E = DataError> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn location_names_everything_it_knows() {
        let loc = Location::file("/d/0004/cameras.pkl")
            .subject("0004")
            .frame("frame_000003")
            .field("extrinsics");
        let msg = DataError::invalid(loc, "NaN at [1][2]").to_string();
        for part in [
            "subject `0004`",
            "frame `frame_000003`",
            "field `extrinsics`",
            "cameras.pkl",
            "NaN",
        ] {
            assert!(msg.contains(part), "{msg} lacks {part}");
        }
    }
}
