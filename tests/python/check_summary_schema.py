"""Validates a summary.json against docs/summary.schema.json with the `jsonschema` package (PyPI),
a JSON Schema implementation no one here wrote: first the schema itself (draft 2020-12), then the
summary. Prints every error with its path; exit status 1 when there is one.

usage: check_summary_schema.py SCHEMA SUMMARY
"""
import json
import sys

from jsonschema import Draft202012Validator


def main() -> int:
    schema_path, summary_path = sys.argv[1], sys.argv[2]
    with open(schema_path) as f:
        schema = json.load(f)
    with open(summary_path) as f:
        summary = json.load(f)
    Draft202012Validator.check_schema(schema)
    errors = sorted(Draft202012Validator(schema).iter_errors(summary), key=lambda e: list(e.absolute_path))
    for e in errors:
        path = ".".join(str(p) for p in e.absolute_path) or "(root)"
        print(f"{path}: {e.message[:300]}")
    print(f"{len(errors)} error(s) in {summary_path}")
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
