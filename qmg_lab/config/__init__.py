"""The configuration: its schema, the wording of its errors, the generated reference, and edits."""
