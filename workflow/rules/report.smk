# Summary: one table of FIT % per campaign, test, channel and model.
# When discover.smk lands, add its discovery.json files to the input here so
# that the "extended" rows are collected too (mbst.summary already reads them).


rule summary:
    input:
        expand("results/{campaign}/identify/correlation.csv", campaign=CAMPAIGNS),
    output:
        report(
            "results/summary.csv",
            caption="../report/summary.rst",
            category="Summary",
            labels={"result": "FIT % over campaigns"},
        ),
    log:
        "logs/summary.log",
    params:
        result_dirs=lambda wildcards, input: [
            os.path.dirname(os.path.dirname(f)) for f in input
        ],
        code=CODE_VERSION,
    conda:
        "../envs/mbst.yaml"
    shell:
        "mbst report summary {params.result_dirs:q} --out {output:q} > {log:q} 2>&1"


# Quick bookkeeping: on a cluster it runs on the submitting machine.
localrules:
    summary,
