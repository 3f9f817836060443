from neumat import report
import pandas as pd


def test_stitch_orders_sections_by_file_name_and_renders_tables(tmp_path):
    (tmp_path / "20_b.md").write_text("## Second\n\n" + report.md_table(pd.DataFrame({"x": [1.5]})))
    (tmp_path / "10_a.md").write_text("## First\n\n![fig](figures/a.png)")
    md, html = report.stitch([tmp_path / "20_b.md", tmp_path / "10_a.md"], "T", "## Config")
    assert md.index("## First") < md.index("## Second") < md.index("## Config")
    assert "<table>" in html and "<h2>First</h2>" in html
    assert '<img alt="fig" src="figures/a.png"' in html
