//! Tables of strings written as CSV or as a markdown pipe table: callers format the numbers once,
//! and the quoting, escaping and alignment rows live here.

use std::fmt::Write as _;

/// How a column's cells line up in the markdown table (CSV has no alignment).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Align {
    Left,
    Right,
}

#[derive(Debug, Clone)]
pub struct Table {
    header: Vec<String>,
    align: Vec<Align>,
    rows: Vec<Vec<String>>,
}

impl Table {
    /// A table with these (header, alignment) columns and no rows yet.
    pub fn new<S: Into<String>>(columns: impl IntoIterator<Item = (S, Align)>) -> Table {
        let (header, align) = columns.into_iter().map(|(h, a)| (h.into(), a)).unzip();
        Table {
            header,
            align,
            rows: Vec::new(),
        }
    }

    /// Adds a row. Panics unless it has one cell per column: a short row is a bug in the caller,
    /// and would silently shift every later column of a CSV.
    pub fn push<S: Into<String>>(&mut self, cells: impl IntoIterator<Item = S>) {
        let row: Vec<String> = cells.into_iter().map(Into::into).collect();
        assert_eq!(
            row.len(),
            self.header.len(),
            "a row of {} cells in a table of {} columns ({:?})",
            row.len(),
            self.header.len(),
            self.header
        );
        self.rows.push(row);
    }

    pub fn header(&self) -> &[String] {
        &self.header
    }

    pub fn rows(&self) -> &[Vec<String>] {
        &self.rows
    }

    /// RFC 4180 CSV, except that lines end in `\n` (what every reader accepts, and what the
    /// files had before): a cell with a comma, a quote or a line break is quoted, quotes doubled.
    pub fn csv(&self) -> String {
        let mut s = String::new();
        for row in std::iter::once(&self.header).chain(&self.rows) {
            let cells: Vec<String> = row.iter().map(|c| csv_cell(c)).collect();
            s += &cells.join(",");
            s.push('\n');
        }
        s
    }

    /// A markdown pipe table, cells padded to their column's width so that the text reads as a
    /// table too (on a terminal, in a diff).
    pub fn markdown(&self) -> String {
        let escaped: Vec<Vec<String>> = std::iter::once(&self.header)
            .chain(&self.rows)
            .map(|row| row.iter().map(|c| markdown_cell(c)).collect())
            .collect();
        // At least 3: the alignment row needs `---`.
        let widths: Vec<usize> = (0..self.header.len())
            .map(|k| {
                escaped
                    .iter()
                    .map(|row| row[k].chars().count())
                    .max()
                    .unwrap_or(0)
                    .max(3)
            })
            .collect();
        let line = |cells: &[String]| {
            let mut l = String::from("|");
            for ((cell, &width), align) in cells.iter().zip(&widths).zip(&self.align) {
                let _ = match align {
                    Align::Left => write!(l, " {cell:<width$} |"),
                    Align::Right => write!(l, " {cell:>width$} |"),
                };
            }
            l.push('\n');
            l
        };
        let rule: Vec<String> = widths
            .iter()
            .zip(&self.align)
            .map(|(&width, align)| match align {
                Align::Left => format!(":{}", "-".repeat(width - 1)),
                Align::Right => format!("{}:", "-".repeat(width - 1)),
            })
            .collect();
        let mut s = line(&escaped[0]);
        s += &line(&rule);
        for row in &escaped[1..] {
            s += &line(row);
        }
        s
    }
}

fn csv_cell(cell: &str) -> String {
    if cell.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", cell.replace('"', "\"\""))
    } else {
        cell.to_string()
    }
}

/// A pipe would end the cell and a line break the row.
fn markdown_cell(cell: &str) -> String {
    cell.replace('|', "\\|").replace(['\n', '\r'], " ")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn table() -> Table {
        let mut t = Table::new([("name", Align::Left), ("value", Align::Right)]);
        t.push(["plain", "1"]);
        t.push(["a, b", "say \"hi\""]);
        t.push(["x|y", "12345"]);
        t
    }

    #[test]
    fn csv_quotes_only_cells_that_need_it() {
        assert_eq!(
            table().csv(),
            "name,value\nplain,1\n\"a, b\",\"say \"\"hi\"\"\"\nx|y,12345\n"
        );
    }

    #[test]
    fn markdown_pads_columns_and_marks_their_alignment() {
        let md = table().markdown();
        let lines: Vec<&str> = md.lines().collect();
        assert_eq!(
            lines,
            [
                "| name  |    value |",
                "| :---- | -------: |",
                "| plain |        1 |",
                "| a, b  | say \"hi\" |",
                "| x\\|y  |    12345 |",
            ]
        );
    }

    #[test]
    #[should_panic(expected = "a row of 1 cells in a table of 2 columns")]
    fn a_short_row_is_refused() {
        table().push(["alone"]);
    }
}
