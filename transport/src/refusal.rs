//! Status codes whose messages cannot be used to reflect a client's input back at it: a
//! refusal names the field and says what is wrong, and quotes at most [`MAX_STATUS_MESSAGE`]
//! bytes of it. An unbounded echo (a 325 kB TOML error, a 3.9 MB actor name) would travel in
//! the `grpc-message` header, which clients refuse above their header limit — they would see
//! RESOURCE_EXHAUSTED instead of the real answer.

use tonic::{Code, Status};

/// Longest status message a server sends (bytes).
pub const MAX_STATUS_MESSAGE: usize = 1024;

/// `message` cut to [`MAX_STATUS_MESSAGE`] bytes at a character boundary, saying how much was cut.
pub fn bounded(message: &str) -> String {
    if message.len() <= MAX_STATUS_MESSAGE {
        return message.to_owned();
    }
    let mut end = MAX_STATUS_MESSAGE - 64;
    while !message.is_char_boundary(end) {
        end -= 1;
    }
    format!("{} … ({} more bytes not shown)", &message[..end], message.len() - end)
}

/// A status of `code` with a [`bounded`] message.
pub fn status(code: Code, message: impl AsRef<str>) -> Status {
    Status::new(code, bounded(message.as_ref()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_huge_echo_is_cut_and_a_short_message_kept() {
        assert_eq!(bounded("gate[3].position: outside the arena"), "gate[3].position: outside the arena");
        let name = "é".repeat(2_000_000);
        let message = format!("actor name {name:?} must be 1-64 characters");
        let cut = status(Code::InvalidArgument, &message);
        assert!(cut.message().len() <= MAX_STATUS_MESSAGE, "{} bytes", cut.message().len());
        assert!(cut.message().starts_with("actor name \"é") && cut.message().contains("more bytes not shown"));
        assert_eq!(cut.code(), Code::InvalidArgument);
    }
}
