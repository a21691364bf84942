//! Cells as the live page reads them, in a size bounded by the cell count.
//!
//! A building's map is long runs of one class, so `[value, count, ...]`
//! is a few hundred bytes where one number a cell would be megabytes. But a
//! map may be anything a robot wrote: one whose class changes at every cell
//! makes two numbers a cell, about 100 MB of JSON for the largest mission
//! (25 million cells), and the first event of every viewer carries the
//! whole map. So a map's rectangle goes as runs only while they are the
//! smaller, else packed two bits a cell in base64 (a third of a byte a
//! cell, 8.3 MB at most); a segmentation, whose labels do not fit in two
//! bits, is sent only while its runs are few.

use base64::Engine as _;
use serde::Serialize;

/// A segmentation's runs sent at most: 8 MB of JSON or so, the size of the
/// largest packed map.
pub(super) const MOST_SEGMENTATION_RUNS: usize = 1 << 20;

/// A rectangle of map classes (each 0 to 3): runs while their JSON (a
/// class digit, its count and two commas a run) is no longer than the
/// packed cells'.
#[derive(Debug, PartialEq, Eq, Serialize)]
#[serde(untagged)]
pub(super) enum Classes {
    /// `{"runs": [class, count, class, count, ...]}`.
    Runs { runs: Vec<u32> },
    /// `{"packed": "…"}`: base64 of 2 bits a cell, cell k in byte k / 4 at
    /// bits 2 (k mod 4) and 2 (k mod 4) + 1.
    Packed { packed: String },
}

impl Classes {
    /// `classes` (row-major, each below 4) in the smaller of the two forms.
    pub(super) fn encode(classes: &[u8]) -> Self {
        let packed_bytes = classes.len().div_ceil(4).div_ceil(3) * 4;
        let runs_bytes: usize = each_run(classes.iter().copied()).map(|(_, n)| 3 + decimal_digits(n)).sum();
        if runs_bytes <= packed_bytes {
            return Self::Runs { runs: runs(classes.iter().map(|&c| u32::from(c))) };
        }
        let mut bytes = vec![0u8; classes.len().div_ceil(4)];
        for (k, &class) in classes.iter().enumerate() {
            bytes[k / 4] |= (class & 3) << (2 * (k % 4));
        }
        Self::Packed { packed: base64::engine::general_purpose::STANDARD.encode(bytes) }
    }
}

/// `(value, count)` for each run of equal values, counts below 2^32.
pub(super) fn each_run<T: PartialEq + Copy>(values: impl Iterator<Item = T>) -> impl Iterator<Item = (T, u32)> {
    let mut values = values.peekable();
    std::iter::from_fn(move || {
        let value = values.next()?;
        let mut count = 1u32;
        while count < u32::MAX && values.next_if(|v| *v == value).is_some() {
            count += 1;
        }
        Some((value, count))
    })
}

/// `[value, count, value, count, ...]`.
pub(super) fn runs(values: impl Iterator<Item = u32>) -> Vec<u32> {
    each_run(values).flat_map(|(v, n)| [v, n]).collect()
}

fn decimal_digits(n: u32) -> usize {
    n.checked_ilog10().map_or(1, |d| d as usize + 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_count_repeats() {
        assert_eq!(runs([1, 1, 1, 0, 2, 2].into_iter()), vec![1, 3, 0, 1, 2, 2]);
        assert_eq!(runs(std::iter::empty()), Vec::<u32>::new());
        assert_eq!(decimal_digits(0), 1);
        assert_eq!(decimal_digits(9), 1);
        assert_eq!(decimal_digits(10), 2);
        assert_eq!(decimal_digits(u32::MAX), 10);
    }

    /// A building's rectangle goes as runs; one whose class changes at
    /// every cell as two bits a cell, which decode to the same classes.
    #[test]
    fn the_smaller_form_is_chosen_and_packed_cells_decode_to_the_classes() {
        let building: Vec<u8> = [vec![1; 500], vec![2; 20], vec![0; 480]].concat();
        assert_eq!(Classes::encode(&building), Classes::Runs { runs: vec![1, 500, 2, 20, 0, 480] });
        assert_eq!(Classes::encode(&[2; 20]), Classes::Runs { runs: vec![2, 20] });

        let fragmented: Vec<u8> = (0..10_001u32).map(|k| (k * 7 % 4) as u8).collect();
        let Classes::Packed { packed } = Classes::encode(&fragmented) else { panic!("runs for a fragmented map") };
        assert_eq!(packed.len(), 10_001usize.div_ceil(4).div_ceil(3) * 4);
        let bytes = base64::engine::general_purpose::STANDARD.decode(&packed).unwrap();
        let decoded: Vec<u8> = (0..fragmented.len()).map(|k| (bytes[k / 4] >> (2 * (k % 4))) & 3).collect();
        assert_eq!(decoded, fragmented);
        // No form costs more than a third of a byte a cell and a little.
        let json = serde_json::to_string(&Classes::encode(&fragmented)).unwrap();
        assert!(json.len() <= fragmented.len() / 3 + 16, "{} bytes for {} cells", json.len(), fragmented.len());
    }
}
