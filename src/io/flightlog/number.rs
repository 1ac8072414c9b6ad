//! The little-endian numbers both flight-log formats store (DataFlash format characters, ULog
//! field types). Pure; no I/O.

/// A little-endian number type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Number {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
}

impl Number {
    /// Bytes it takes.
    pub fn size(self) -> usize {
        match self {
            Number::I8 | Number::U8 => 1,
            Number::I16 | Number::U16 => 2,
            Number::I32 | Number::U32 | Number::F32 => 4,
            Number::I64 | Number::U64 | Number::F64 => 8,
        }
    }

    /// The value in the first [`Number::size`] bytes of `b`; `None` when `b` is shorter.
    pub fn read(self, b: &[u8]) -> Option<f64> {
        let b = b.get(..self.size())?;
        Some(match self {
            Number::I8 => b[0] as i8 as f64,
            Number::U8 => b[0] as f64,
            Number::I16 => i16::from_le_bytes(b.try_into().ok()?) as f64,
            Number::U16 => u16::from_le_bytes(b.try_into().ok()?) as f64,
            Number::I32 => i32::from_le_bytes(b.try_into().ok()?) as f64,
            Number::U32 => u32::from_le_bytes(b.try_into().ok()?) as f64,
            Number::I64 => i64::from_le_bytes(b.try_into().ok()?) as f64,
            Number::U64 => u64::from_le_bytes(b.try_into().ok()?) as f64,
            Number::F32 => f32::from_le_bytes(b.try_into().ok()?) as f64,
            Number::F64 => f64::from_le_bytes(b.try_into().ok()?),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::Number;

    #[test]
    fn reads_each_type_little_endian_and_refuses_short_input() {
        let b = [0xFEu8, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF];
        assert_eq!(Number::I8.read(&b), Some(-2.0));
        assert_eq!(Number::U8.read(&b), Some(254.0));
        assert_eq!(Number::I16.read(&b), Some(-2.0));
        assert_eq!(Number::U16.read(&b), Some(65534.0));
        assert_eq!(Number::I32.read(&b), Some(-2.0));
        assert_eq!(Number::I64.read(&b), Some(-2.0));
        assert_eq!(Number::F32.read(&1.5f32.to_le_bytes()), Some(1.5));
        assert_eq!(Number::F64.read(&(-0.25f64).to_le_bytes()), Some(-0.25));
        assert_eq!(Number::U32.read(&b[..3]), None);
        assert_eq!(Number::F64.read(&b[..7]), None);
    }
}
